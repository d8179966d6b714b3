// The participant page: information, consent, demographics, instructions, trials, thanks.
// Server state decides where a participant is; this page keeps only the session id and token (localStorage),
// so a reload resumes at the current trial.  Nothing here knows which side shows which animation.
"use strict";

(() => {
  const slug = decodeURIComponent(location.pathname.split("/").filter(Boolean).pop() || "");
  // A researcher's preview link (?preview=<token>): a pilot session, kept apart from a real one in this browser.
  const preview = new URLSearchParams(location.search).get("preview");
  const storeKey = preview ? `animstudy-pilot:${slug}` : `animstudy:${slug}`;
  const $ = (id) => document.getElementById(id);
  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
  const PAGES = ["info", "consent", "demographics", "instructions", "trial", "thanks", "withdrawn", "message"];
  const LOAD_ATTEMPTS = 4;

  let study = null;
  let creds = readCreds();
  let current = null; // the trial on screen
  let viewed = false; // watched one full loop
  let playback = null; // measurements of the current trial's playback
  const videos = new Map(); // url -> Promise of an object URL of the fully downloaded file
  let device = null; // what the device gate measured last
  let gated = false; // the gate is on screen (the flow underneath keeps its state)

  function readCreds() {
    try { return JSON.parse(localStorage.getItem(storeKey)); } catch { return null; }
  }
  function saveCreds() { localStorage.setItem(storeKey, JSON.stringify(creds)); }
  function clearCreds() { localStorage.removeItem(storeKey); creds = null; }

  function uuid() {
    if (crypto.randomUUID) return crypto.randomUUID();
    const b = crypto.getRandomValues(new Uint8Array(16));
    return Array.from(b, (x) => x.toString(16).padStart(2, "0")).join("");
  }

  // The page's own wording: the study's [page] chrome (defaults: server/studies/page.py), {name} filled in.
  let chrome = {};
  function t(key, values = {}) {
    return String(chrome[key] ?? key).replace(/\{(\w+)\}/g, (m, name) => (name in values ? values[name] : m));
  }
  function applyPage(page) {
    chrome = page.chrome;
    document.documentElement.lang = page.lang;
    document.documentElement.dir = page.dir;
    document.querySelectorAll("[data-t]").forEach((el) => { el.textContent = t(el.dataset.t); });
  }

  function status(text) { $("status").textContent = text || ""; }

  // --- device gate ------------------------------------------------------------------------------------------
  // The pair video must show each character at no less than `min_scale` of its rendered size.  The scale the
  // video would get is computed from the same box the stylesheet gives it (stage width, --stage-max-height), so
  // the gate can decide before consent, while the trial page is still hidden, and again on resize/rotation.
  // The study's [page.device_gate] sets min_scale; the video's width/height attributes are the rendered default
  // size until the trial's video tells its own.
  function gateSettings() {
    const video = $("video");
    return { video_width: Number(video.getAttribute("width")), video_height: Number(video.getAttribute("height")),
             ...study.page.device_gate };
  }

  function px(style, name) { return parseFloat(style.getPropertyValue(name)) || 0; }

  function measureDevice() {
    const settings = gateSettings();
    const video = $("video");
    const width = video.videoWidth || settings.video_width;
    const height = video.videoHeight || settings.video_height;
    const main = getComputedStyle($("main"));
    const trial = getComputedStyle($("page-trial"));
    const stage = Math.min(
      $("main").clientWidth - px(main, "padding-left") - px(main, "padding-right")
        - px(trial, "padding-left") - px(trial, "padding-right")
        - px(trial, "border-left-width") - px(trial, "border-right-width"),
      1284);
    const maxHeight = window.innerHeight * px(getComputedStyle(document.documentElement), "--stage-max-height") / 100;
    const scale = Math.min(1, stage / width, maxHeight / height);
    return { viewport_width: window.innerWidth, viewport_height: window.innerHeight,
             device_pixel_ratio: window.devicePixelRatio, video_width: width, video_height: height,
             scale: Math.round(scale * 1000) / 1000, scaled: scale < 1, passed: scale >= settings.min_scale };
  }

  // Returns whether the participant may go on.
  function checkGate() {
    device = measureDevice();
    if (device.passed === !gated) return !gated;
    gated = !device.passed;
    $("gate").hidden = !gated;
    $("flow").hidden = gated;
    $("withdraw").hidden = gated || $("withdraw").dataset.hiddenByPage === "1";
    const video = $("video");
    if (gated) {
      video.pause();
      $("gate-title").tabIndex = -1;
      $("gate-title").focus({ preventScroll: true });
    } else if (!$("page-trial").hidden && video.src && $("play").hidden) {
      video.play().catch(() => refusedAutoplay());
    }
    return !gated;
  }
  let resizeTimer = null;
  const onResize = () => { clearTimeout(resizeTimer); resizeTimer = setTimeout(() => { if (study) checkGate(); }, 150); };
  window.addEventListener("resize", onResize);
  window.addEventListener("orientationchange", onResize);

  function show(page) {
    for (const p of PAGES) $(`page-${p}`).hidden = p !== page;
    const noWithdraw = !creds || ["withdrawn", "thanks"].includes(page);
    $("withdraw").dataset.hiddenByPage = noWithdraw ? "1" : "";
    $("withdraw").hidden = noWithdraw || gated;
    if (page !== "trial") stopVideo();
    const heading = $(`page-${page}`).querySelector("h2");
    if (heading) { heading.tabIndex = -1; heading.focus({ preventScroll: true }); }
  }

  function message(title, text, retry) {
    $("message-title").textContent = title;
    $("message-text").textContent = text;
    $("message-retry").hidden = !retry;
    $("message-retry").onclick = retry || null;
    show("message");
  }

  function paragraphs(element, text) {
    element.replaceChildren(...String(text || "").split(/\n\s*\n/).map((part) => {
      const p = document.createElement("p");
      p.textContent = part.trim();
      return p;
    }));
  }

  async function api(method, path, body) {
    const headers = { Accept: "application/json" };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    if (creds) headers.Authorization = `Bearer ${creds.token}`;
    return fetch(`/api/v1${path}`, { method, headers, body: body === undefined ? undefined : JSON.stringify(body),
                                     cache: "no-store" });
  }

  // Network calls that must get through: retried with backoff on network errors and 5xx answers.
  async function persist(call) {
    for (let attempt = 0; ; attempt++) {
      try {
        const r = await call();
        if (r.status < 500) { status(""); return r; }
      } catch { /* offline or connection dropped: try again */ }
      status(t("retrying"));
      await sleep(Math.min(10000, 500 * 2 ** attempt));
    }
  }

  // --- start and resume ---------------------------------------------------------------------------------
  async function start() {
    const r = await persist(() => fetch(`/api/v1/studies/${encodeURIComponent(slug)}${preview ? `?preview=${encodeURIComponent(preview)}` : ""}`));
    if (!r.ok) {
      const defaults = await persist(() => fetch("/api/v1/page-defaults"));
      applyPage(await defaults.json());
      message(t("not_found_title"), t("not_found_text"));
      return;
    }
    study = await r.json();
    applyPage(study.page);
    $("study-title").textContent = study.title;
    document.title = study.title;
    paragraphs($("info-text"), study.texts.information);
    $("contact-text").textContent = study.texts.contact || "";
    paragraphs($("consent-text"), study.texts.consent);
    paragraphs($("instructions-text"), study.texts.instructions);
    paragraphs($("thanks-text"), study.texts.thanks);
    $("scale-question").textContent = study.scale.question;
    buildAnswers(study.scale);
    buildQuestions(study.questions);
    checkGate();
    if (creds) { await resume(); return; }
    if (study.state !== "open" && !(preview && study.state === "draft")) {
      message(t("closed_title"), t("closed_text")); return;
    }
    show("info");
  }

  // The answers of the study's format, in the order of its ids (served by the API: the page spells none), each
  // a radio button with its key (1..n) and the study's label.  Two-sided answers (2AFC) keep left on the left and
  // side by side on every screen and in right-to-left languages: they name sides of the video.
  function buildAnswers(scale) {
    const set = $("vote-form").querySelector("fieldset");
    set.querySelectorAll("label").forEach((el) => el.remove());
    set.dataset.format = scale.format;
    set.style.setProperty("--answers", String(scale.choices.length));
    scale.choices.forEach((id, i) => {
      const label = document.createElement("label");
      const input = document.createElement("input");
      input.type = "radio";
      input.name = "choice";
      input.value = id;
      const key = document.createElement("kbd");
      key.textContent = String(i + 1);
      const text = document.createElement("span");
      text.className = "choice-label";
      text.dir = "auto";
      text.textContent = scale.labels[i];
      label.append(input, key, " ", text);
      set.append(label);
    });
  }

  // The study's questions, one fieldset each: radio buttons for a choice (valued by the choice id) or a Likert
  // scale (valued 1..n), a number field (with its range and unit) or a short text field, named by the question id.
  function buildQuestions(questions) {
    const form = $("demographics-form");
    form.querySelectorAll("fieldset").forEach((f) => f.remove());
    for (const q of questions) {
      const set = document.createElement("fieldset");
      set.dataset.type = q.type || "choice";
      const legend = document.createElement("legend");
      legend.textContent = q.text;
      legend.id = `q-${q.id}-legend`;
      set.append(legend);
      const type = q.type || "choice";
      if (type === "choice" || type === "likert") {
        const options = type === "choice" ? q.choices.map((c) => [c.id, c.label])
                                          : q.labels.map((label, i) => [String(i + 1), label]);
        if (type === "likert") set.classList.add("likert");
        options.forEach(([value, text], i) => {
          const label = document.createElement("label");
          const input = Object.assign(document.createElement("input"), { type: "radio", name: q.id, value,
                                                                           required: i === 0 });
          label.append(input, ` ${text}`);
          set.append(label);
        });
      } else {
        const label = document.createElement("label");
        const input = document.createElement("input");
        Object.assign(input, { name: q.id, required: true });
        input.setAttribute("aria-labelledby", legend.id);
        if (type === "number") {
          Object.assign(input, { type: "number", step: q.integer ? "1" : "any", inputMode: q.integer ? "numeric" : "decimal" });
          if (q.min !== null && q.min !== undefined) input.min = String(q.min);
          if (q.max !== null && q.max !== undefined) input.max = String(q.max);
        } else {
          Object.assign(input, { type: "text", maxLength: q.max_length, autocomplete: "off" });
        }
        label.append(input);
        if (type === "number" && q.unit) label.append(` ${q.unit}`);
        set.append(label);
      }
      form.insertBefore(set, form.querySelector("button"));
    }
  }

  // A form value as the question's type wants it: a number for number and Likert questions.
  function answerValue(q, raw) {
    if (raw === null || raw === "") return null;
    const type = q.type || "choice";
    if (type === "number" || type === "likert") return Number(raw);
    return type === "text" ? String(raw).trim() || null : raw;
  }

  async function resume() {
    const r = await persist(() => api("GET", `/sessions/${creds.session_id}`));
    if ([401, 403, 404].includes(r.status)) { clearCreds(); await start(); return; }
    const state = await r.json();
    if (state.state === "completed") { thanks(state); return; }
    if (!state.demographics_given) { show("demographics"); return; }
    if (!creds.instructed) { show("instructions"); return; }
    await nextTrial();
  }

  $("info-next").addEventListener("click", () => show("consent"));
  $("consent-box").addEventListener("change", (e) => { $("consent-next").disabled = !e.target.checked; });
  $("consent-next").addEventListener("click", async () => {
    if (!$("consent-box").checked) return;
    $("consent-next").disabled = true;
    const params = new URLSearchParams(location.search);
    const external = {};
    for (const name of study.parameters) if (params.get(name)) external[name] = params.get(name).slice(0, 200);
    const body = { consent: true, external: Object.keys(external).length ? external : null, device: measureDevice(),
                   ...(preview ? { preview } : {}) };
    const r = await persist(() => api("POST", `/studies/${encodeURIComponent(slug)}/sessions`, body));
    if (r.status !== 201) { message(t("cannot_start_title"), t("closed_text")); return; }
    const created = await r.json();
    creds = { session_id: created.session_id, token: created.token, instructed: false };
    saveCreds();
    show("demographics");
  });

  $("demographics-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const form = new FormData(e.target);
    const body = Object.fromEntries(study.questions.map((q) => [q.id, answerValue(q, form.get(q.id))]));
    if (Object.values(body).some((v) => v === null || Number.isNaN(v))) return;
    const r = await persist(() => api("PUT", `/sessions/${creds.session_id}/demographics`, body));
    if (r.ok) show("instructions");
    else if (r.status === 401) { clearCreds(); await start(); }
    else if (r.status === 422) { // the server's checks: shown on the field, as the browser's own would be
      const detail = (await r.json().catch(() => ({}))).detail || [];
      for (const d of Array.isArray(detail) ? detail : []) {
        const input = e.target.querySelector(`[name="${CSS.escape(String((d.loc || [])[1]))}"]`);
        if (!input) continue;
        input.setCustomValidity(d.msg);
        input.reportValidity();
        input.addEventListener("input", () => input.setCustomValidity(""), { once: true });
        break;
      }
    }
  });

  // The study may ask for full screen; the request must come from this click (a user gesture). Leaving full
  // screen is reported, and every vote says whether it was cast in full screen.
  function requestFullscreen() {
    if (!study.page.fullscreen || document.fullscreenElement) return;
    const refused = (error) => persist(() => api("POST", `/sessions/${creds.session_id}/events`,
                                                 { kind: "fullscreen_refused", detail: { error: String(error) } }));
    if (!document.fullscreenEnabled) { refused("not supported"); return; }
    document.documentElement.requestFullscreen().catch(refused);
  }
  document.addEventListener("fullscreenchange", () => {
    if (document.fullscreenElement || !study || !study.page.fullscreen || !creds.session_id) return;
    persist(() => api("POST", `/sessions/${creds.session_id}/events`,
                      { kind: "fullscreen_exit", trial_id: current ? current.trial_id : null }));
  });

  $("instructions-next").addEventListener("click", async () => {
    creds.instructed = true;
    saveCreds();
    requestFullscreen();
    await nextTrial();
  });

  // --- videos ---------------------------------------------------------------------------------------------
  // A trial's video is downloaded completely before it is shown (and the next one in the background), so
  // playback never waits for the network; failures are retried, and a final failure is reported.
  function fetchVideo(url, onProgress) {
    if (!videos.has(url)) {
      const promise = (async () => {
        let lastError = null;
        for (let attempt = 0; attempt < LOAD_ATTEMPTS; attempt++) {
          try {
            const r = await fetch(url);
            if (!r.ok) throw new Error(`HTTP ${r.status}`);
            const total = Number(r.headers.get("Content-Length")) || 0;
            const reader = r.body.getReader();
            const chunks = [];
            let received = 0;
            for (;;) {
              const { done, value } = await reader.read();
              if (done) break;
              chunks.push(value);
              received += value.length;
              if (onProgress && total) onProgress(received / total);
            }
            return URL.createObjectURL(new Blob(chunks, { type: "video/mp4" }));
          } catch (error) {
            lastError = error;
            await sleep(400 * 2 ** attempt);
          }
        }
        throw lastError;
      })();
      videos.set(url, promise);
      promise.catch(() => videos.delete(url));
    } else if (onProgress) {
      onProgress(0.5);
    }
    return videos.get(url);
  }

  function stopVideo() {
    const video = $("video");
    video.pause();
    video.removeAttribute("src");
    video.load();
  }

  function measure(video, onFirstLoop) {
    // Frame-accurate: requestVideoFrameCallback reports every presented frame; a jump in media time larger than
    // 1.5 frames is a hitch, a jump backwards is the loop restarting.  The minimum viewing time is counted on the
    // media clock (the first loop really shown), not by a wall-clock timer that a slow machine can outrun.
    const m = { presented: 0, hitches: 0, max_gap_ms: 0, stalls: 0, loops: 0, started_ms: performance.now() };
    let last = null;
    const frameMs = 1000 / 30;
    const looped = () => {
      m.loops++;
      if (m.loops === 1) onFirstLoop();
    };
    const onFrame = (_now, meta) => {
      if (playback !== m) return;
      m.presented++;
      if (last !== null) {
        const dt = (meta.mediaTime - last) * 1000;
        if (dt < 0) looped();
        else if (dt > 1.5 * frameMs) { m.hitches++; m.max_gap_ms = Math.max(m.max_gap_ms, Math.round(dt)); }
      }
      last = meta.mediaTime;
      video.requestVideoFrameCallback(onFrame);
    };
    if (video.requestVideoFrameCallback) {
      video.requestVideoFrameCallback(onFrame);
      video.ontimeupdate = null;
    } else {
      // Coarser fallback for browsers without requestVideoFrameCallback: the media clock going backwards.
      video.ontimeupdate = () => {
        if (playback !== m) return;
        if (last !== null && video.currentTime < last) looped();
        last = video.currentTime;
      };
    }
    // Waiting for data is a stall; the seek back to the start of each loop is not.
    video.onwaiting = () => { if (playback === m && !video.seeking) m.stalls++; };
    return m;
  }

  function playbackReport() {
    const video = $("video");
    const q = video.getVideoPlaybackQuality ? video.getVideoPlaybackQuality() : null;
    const m = playback || {};
    return {
      frames_presented: m.presented || 0, hitches: m.hitches || 0, max_gap_ms: m.max_gap_ms || 0,
      stalls: m.stalls || 0, loops: m.loops || 0,
      dropped_frames: q ? q.droppedVideoFrames : null, total_frames: q ? q.totalVideoFrames : null,
      watched_ms: m.started_ms ? Math.round(performance.now() - m.started_ms) : 0,
      autoplay_refused: Boolean(m.autoplay_refused), play_wait_ms: m.play_wait_ms ?? null,
      fullscreen: study.page.fullscreen ? Boolean(document.fullscreenElement) : null,
    };
  }

  // --- trials ---------------------------------------------------------------------------------------------
  // `known`: the next trial as the vote's answer gave it (null: none left); otherwise asked from the server.
  async function nextTrial(known) {
    show("trial");
    $("vote-form").reset();
    $("vote-submit").disabled = true;
    viewed = false;
    if (known === null) { await finish(); return; }
    let trial = known;
    if (trial === undefined) {
      const r = await persist(() => api("GET", `/sessions/${creds.session_id}/next`));
      if (r.status === 204) { await finish(); return; }
      if ([401, 403, 404].includes(r.status)) { clearCreds(); await start(); return; }
      trial = await r.json();
    }
    current = trial;
    $("trial-progress").textContent = t("progress", { index: trial.index + 1, total: trial.total })
      + (trial.practice ? ` ${t("practice")}` : "");
    const loading = $("loading");
    loading.hidden = false;
    $("loading-bar").value = 0;
    $("loading-text").textContent = t("loading");
    let url;
    try {
      url = await fetchVideo(trial.video_url, (f) => {
        $("loading-bar").value = Math.round(f * 100);
        $("loading-text").textContent = t("loading_percent", { percent: Math.round(f * 100) });
      });
    } catch (error) {
      await persist(() => api("POST", `/sessions/${creds.session_id}/events`,
                              { kind: "load_failure", trial_id: trial.trial_id, detail: { error: String(error) } }));
      message(t("load_failed_title"), t("load_failed_text"), () => nextTrial());
      return;
    }
    if (current !== trial) return;
    if (trial.preload_url) fetchVideo(trial.preload_url).catch(() => {});
    const video = $("video");
    video.src = url;
    await new Promise((resolve) => {
      if (video.readyState >= 3) resolve();
      else video.addEventListener("canplay", resolve, { once: true });
    });
    loading.hidden = true;
    checkGate(); // now with the real video's size
    playback = measure(video, () => {
      if (current !== trial) return;
      viewed = true;
      updateSubmit();
    });
    $("play").hidden = true;
    if (gated) video.pause();
    else {
      try {
        await video.play();
      } catch (error) {
        if (error.name === "NotAllowedError" && current === trial) { refusedAutoplay(); return; }
      }
    }
    $("vote-form").querySelector("input").focus({ preventScroll: true });
  }

  // The browser refused to start the video without a click: a Play button, and the refusal goes with the vote.
  function refusedAutoplay() {
    const m = playback;
    if (!m) return;
    m.autoplay_refused = true;
    const refusedAt = performance.now();
    const button = $("play");
    button.hidden = false;
    button.focus({ preventScroll: true });
    button.onclick = async () => {
      try { await $("video").play(); } catch { return; }
      button.hidden = true;
      m.started_ms = performance.now(); // the viewing time starts with the click
      if (m.play_wait_ms == null) m.play_wait_ms = Math.round(performance.now() - refusedAt);
      $("vote-form").querySelector("input").focus({ preventScroll: true });
    };
  }

  function updateSubmit() {
    const chosen = new FormData($("vote-form")).get("choice");
    $("vote-submit").disabled = !(viewed && chosen);
    if (chosen && !viewed) status(t("watch_first"));
    else status("");
  }
  $("vote-form").addEventListener("change", updateSubmit);

  $("vote-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const choice = new FormData(e.target).get("choice");
    if (!choice || !viewed || !current || $("vote-submit").disabled) return;
    const trial = current;
    current = null;
    $("vote-submit").disabled = true;
    status(t("saving"));
    const body = { choice, rt_ms: Math.round(playbackReport().watched_ms), idempotency_key: uuid(),
                   playback: playbackReport(), device };
    // The page moves on only once the server has the vote: retried until acknowledged (same idempotency key,
    // so a retry never creates a second vote).
    const r = await persist(() => api("POST", `/sessions/${creds.session_id}/trials/${trial.trial_id}/vote`, body));
    status(r.ok ? t("saved") : "");
    if ([401, 403].includes(r.status)) { clearCreds(); await start(); return; }
    // 201/200: stored, and the answer names the next trial; 409: the server already moved on, ask it where to.
    await nextTrial(r.ok ? (await r.json()).next : undefined);
  });

  document.addEventListener("keydown", (e) => {
    if ($("page-trial").hidden || gated || e.altKey || e.ctrlKey || e.metaKey) return;
    const inputs = $("vote-form").querySelectorAll("input[name=choice]");
    if (e.key >= "1" && e.key <= "9" && Number(e.key) <= inputs.length) {
      const input = inputs[Number(e.key) - 1];
      input.checked = true;
      input.focus({ preventScroll: true });
      updateSubmit();
      e.preventDefault();
    } else if (e.key === "Enter" && !$("vote-submit").disabled) {
      $("vote-form").requestSubmit();
      e.preventDefault();
    }
  });

  // --- the end ----------------------------------------------------------------------------------------------
  async function finish() {
    const r = await persist(() => api("GET", `/sessions/${creds.session_id}`));
    thanks(r.ok ? await r.json() : {});
  }

  function thanks(state) {
    show("thanks");
    $("completion").hidden = !state.completion_code;
    $("completion-code").textContent = state.completion_code || "";
    $("completion-link-line").hidden = !state.completion_url;
    if (state.completion_url) {
      $("completion-link").href = state.completion_url;
      setTimeout(() => { location.href = state.completion_url; }, 5000);
    }
  }

  $("withdraw").addEventListener("click", async () => {
    if (!creds || !confirm(t("withdraw_confirm"))) return;
    const r = await persist(() => api("POST", `/sessions/${creds.session_id}/withdraw`));
    if (r.ok || r.status === 401) { clearCreds(); show("withdrawn"); }
  });

  start();
})();
