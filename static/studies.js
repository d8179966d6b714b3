// The studies page of the dashboard: every study the researcher may manage, with state and counts; create one
// from a study file, edit its texts while allowed, open and close, links to its participant page and results; a
// draft's motion files (upload, inspection results, delete) and the build of their clips with its progress.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const TEXTS = ["information", "consent", "consent_version", "contact", "instructions", "thanks"];

  const api = Researcher.api;

  // The error details of a 4xx answer, one per line.
  async function problems(r) {
    const body = await r.json().catch(() => ({}));
    if (Array.isArray(body.detail)) {
      return body.detail.map((d) => (d.loc && d.loc.length > 1 ? `${d.loc.slice(1).join(".")}: ${d.msg}` : d.msg)).join("\n");
    }
    return body.detail || `HTTP ${r.status}`;
  }

  function link(text, href) {
    const a = document.createElement("a");
    a.textContent = text;
    a.href = href;
    return a;
  }

  function button(text, onclick) {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = text;
    b.addEventListener("click", onclick);
    return b;
  }

  // The name rule of animations and conditions, as the server defines it (GET /api/v1/constants).
  async function namePattern() {
    const r = await fetch("/api/v1/constants", { cache: "no-store" });
    if (r.ok) $("asset-name").pattern = (await r.json()).name_pattern;
  }

  async function refresh() {
    $("login").hidden = true;
    const r = await api("/studies");
    if (!r.ok) { $("status").textContent = `Cannot load the studies (HTTP ${r.status}).`; return; }
    const studies = await r.json();
    $("studies").hidden = false;
    $("actions").hidden = false;
    const { table: t, body } = Researcher.newTable(["study", "title", "state", "started", "completed", "votes", "trials", "links", "actions"]);
    for (const s of studies) {
      const tr = body.insertRow();
      tr.dataset.slug = s.slug;
      for (const v of [s.slug, s.title]) tr.insertCell().textContent = v;
      const badge = document.createElement("span");
      badge.className = `badge ${s.state}`;
      badge.textContent = s.state;
      tr.insertCell().append(badge);
      for (const v of [s.started, s.completed, s.votes, s.trials_total]) tr.insertCell().textContent = v;
      const links = tr.insertCell();
      links.append(link("participant page", s.participant_url), " ", link("results", `/dashboard?study=${encodeURIComponent(s.slug)}`));
      const actions = tr.insertCell();
      actions.className = "actions";
      const action = s.state === "open" ? "close" : "open";
      actions.append(button(action === "open" ? "Open" : "Close", () => setState(s.slug, action)));
      if (s.editable.texts) actions.append(button("Edit texts", () => edit(s.slug)));
      if (s.state === "draft") actions.append(button("Motion files", () => showAssets(s.slug)));
      if (s.editable.design) actions.append(button("Delete", () => remove(s.slug)));
    }
    $("table-studies").replaceChildren(t);
    $("status").textContent = `${studies.length} ${studies.length === 1 ? "study" : "studies"}`;
  }

  async function setState(slug, action) {
    const r = await api(`/studies/${encodeURIComponent(slug)}/${action}`, { method: "POST" });
    if (!r.ok) $("status").textContent = await problems(r);
    await refresh();
  }

  async function remove(slug) {
    if (!confirm(`Delete the draft study ${slug}?`)) return;
    const r = await api(`/studies/${encodeURIComponent(slug)}`, { method: "DELETE" });
    if (!r.ok) $("status").textContent = await problems(r);
    await refresh();
  }

  async function edit(slug) {
    const r = await api(`/studies/${encodeURIComponent(slug)}/definition`);
    if (!r.ok) { $("status").textContent = await problems(r); return; }
    const definition = await r.json();
    $("edit-slug").textContent = slug;
    $("edit-form").dataset.slug = slug;
    $("edit-errors").textContent = "";
    $("edit-fields").replaceChildren(...TEXTS.map((name) => {
      const p = document.createElement("p");
      const label = document.createElement("label");
      label.textContent = name;
      label.htmlFor = `text-${name}`;
      const area = document.createElement(name === "consent_version" ? "input" : "textarea");
      area.id = `text-${name}`;
      area.name = name;
      area.value = definition.texts[name];
      if (area.tagName === "TEXTAREA") area.rows = 4;
      area.style.width = "100%";
      p.append(label, document.createElement("br"), area);
      return p;
    }));
    $("edit-panel").hidden = false;
  }

  // --- motion files and their build ---
  const BUILD_POLL_MS = 1000;
  const STAGES = { queued: "Waiting to start", building: "Building clips", rendering: "Rendering videos",
                   study: "Updating the study", done: "Done" };
  let assetsSlug = null;
  let polling = null;
  const assetsUrl = (slug, rest = "") => `/studies/${encodeURIComponent(slug)}/assets${rest}`;

  // "LeftUpLeg = thigh_l" lines or a JSON object -> {character joint: file joint}; throws a message.
  function parseMapping(text) {
    const t = text.trim();
    if (!t) return {};
    if (t.startsWith("{")) {
      try { return JSON.parse(t); } catch (err) { throw new Error(`Joint mapping: not JSON (${err.message})`); }
    }
    const out = {};
    for (const [n, line] of t.split("\n").entries()) {
      if (!line.trim()) continue;
      const m = line.match(/^\s*([^=\s]+)\s*=\s*"?([^"]+?)"?\s*$/);
      if (!m) throw new Error(`Joint mapping, line ${n + 1}: write character joint = file joint`);
      out[m[1]] = m[2];
    }
    return out;
  }
  const mappingText = (m) => Object.entries(m || {}).map(([k, v]) => `${k} = ${v}`).join("\n");

  function cellText(a) {
    const r = a.report;
    const suggested = `${r.suggested.kind}, frames ${r.suggested.frames[0]}..${r.suggested.frames[1]} (${r.suggested.reason})`;
    const given = r.options || {};
    const read = `${r.units}${given.units ? " (given)" : ""}, ${r.up_axis.toUpperCase()} up${given.up_axis ? " (given)" : ""}` +
      (given.mapping ? `, ${Object.keys(given.mapping).length} joints mapped by hand` : "");
    return [a.name, a.filename, `${(a.size_bytes / 1024).toFixed(1)} KiB`, r.joints, r.convention,
            read, Number(r.fps).toFixed(2), r.frames, suggested,
            `${a.kind}, ${a.frames[0]}..${a.frames[1]}`];
  }

  async function showAssets(slug) {
    assetsSlug = slug;
    $("assets-slug").textContent = slug;
    $("asset-errors").textContent = "";
    $("assets-panel").hidden = false;
    await loadAssets();
    $("assets-title").focus();
  }

  async function loadAssets() {
    const slug = assetsSlug;
    const r = await api(assetsUrl(slug));
    if (!r.ok) { $("asset-errors").textContent = await problems(r); return; }
    const { assets, build, kinds } = await r.json();
    $("asset-kind").replaceChildren(...kinds.map((k) => new Option(k, k)));
    $("asset-edit").hidden = true;
    const { table: t, body } = Researcher.newTable(["animation", "file", "size", "joints", "convention", "units", "fps", "frames", "suggested", "built as", ""]);
    for (const a of assets) {
      const tr = body.insertRow();
      tr.dataset.asset = a.name;
      for (const v of cellText(a)) tr.insertCell().textContent = v;
      const change = button("Change", () => editAsset(a));
      change.setAttribute("aria-label", `Change how ${a.filename} is built`);
      const del = button("Delete", () => removeAsset(slug, a.name));
      del.setAttribute("aria-label", `Delete ${a.filename}`);
      const cell = tr.insertCell();
      cell.className = "actions";
      cell.append(change, del);
    }
    $("table-assets").replaceChildren(assets.length ? t : document.createTextNode("No motion files yet."));
    $("build-button").disabled = !assets.length;
    showBuild(build);
  }

  function showBuild(job) {
    $("build").hidden = !job;
    const active = job && (job.state === "queued" || job.state === "running");
    $("build-button").disabled = active || !$("table-assets").querySelector("tbody tr");
    if (!job) return;
    const bar = $("build-progress");
    bar.max = Math.max(1, job.total);
    bar.value = job.state === "done" ? bar.max : job.done;
    $("build-stage").textContent = `${STAGES[job.stage] || job.stage} (${job.done} of ${job.total})`;
    $("build-status").textContent = job.state === "failed" ? "The build failed." : job.message;
    $("build-error").textContent = job.error || "";
    $("build").dataset.state = job.state;
    if (active && !polling) polling = setTimeout(pollBuild, BUILD_POLL_MS);
  }

  async function pollBuild() {
    polling = null;
    if (!assetsSlug) return;
    const r = await api(assetsUrl(assetsSlug, "/build"));
    if (!r.ok) return;
    const job = await r.json();
    showBuild(job);
    if (job && job.state === "done") await refresh();  // the design (and the trial count) changed
  }

  function editAsset(a) {
    const form = $("asset-edit");
    form.dataset.asset = a.name;
    $("asset-edit-name").textContent = a.filename;
    $("asset-kind").value = a.kind;
    $("asset-first").value = a.frames[0];
    $("asset-last").value = a.frames[1];
    $("asset-first").max = $("asset-last").max = a.report.frames - 1;
    const given = a.report.options || {};
    $("asset-units-edit").value = given.units || "auto";
    $("asset-up-edit").value = given.up_axis || "auto";
    $("asset-mapping-edit").value = mappingText(given.mapping);
    $("asset-unfaithful").checked = Boolean(a.report.accept_unfaithful);
    form.dataset.read = JSON.stringify([$("asset-units-edit").value, $("asset-up-edit").value, $("asset-mapping-edit").value]);
    form.hidden = false;
    $("asset-kind").focus();
  }

  $("asset-edit").addEventListener("submit", async (e) => {
    e.preventDefault();
    const body = { kind: $("asset-kind").value, frames: [Number($("asset-first").value), Number($("asset-last").value)] };
    body.accept_unfaithful = $("asset-unfaithful").checked;
    const read = [$("asset-units-edit").value, $("asset-up-edit").value, $("asset-mapping-edit").value];
    if (JSON.stringify(read) !== e.target.dataset.read) {  // read the file anew: its new suggestion is taken
      try { body.mapping = parseMapping(read[2]); } catch (err) { $("asset-errors").textContent = err.message; return; }
      body.units = read[0];
      body.up_axis = read[1];
      delete body.kind;
      delete body.frames;
    }
    const r = await api(assetsUrl(assetsSlug, `/${encodeURIComponent(e.target.dataset.asset)}`), {
      method: "PATCH", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    $("asset-errors").textContent = r.ok ? "" : await problems(r);
    if (r.ok) await loadAssets();
  });
  $("asset-edit-cancel").addEventListener("click", () => { $("asset-edit").hidden = true; });

  async function removeAsset(slug, name) {
    if (!confirm(`Delete the motion file of ${name}?`)) return;
    const r = await api(assetsUrl(slug, `/${encodeURIComponent(name)}`), { method: "DELETE" });
    $("asset-errors").textContent = r.ok ? "" : await problems(r);
    await loadAssets();
  }

  $("asset-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const file = $("asset-file").files[0];
    if (!file || !assetsSlug) return;
    const params = new URLSearchParams({ filename: file.name });
    if ($("asset-name").value) params.set("name", $("asset-name").value);
    if ($("asset-units").value !== "auto") params.set("units", $("asset-units").value);
    if ($("asset-up").value !== "auto") params.set("up", $("asset-up").value);
    try {
      const mapping = parseMapping($("asset-mapping").value);
      if (Object.keys(mapping).length) params.set("mapping", JSON.stringify(mapping));
    } catch (err) { $("asset-errors").textContent = err.message; return; }
    $("asset-errors").textContent = "";
    $("status").textContent = `Uploading ${file.name}…`;
    const r = await api(assetsUrl(assetsSlug, `?${params}`), {
      method: "POST", headers: { "Content-Type": "application/octet-stream" }, body: file });
    $("status").textContent = r.ok ? `${file.name} uploaded.` : `${file.name} was not stored.`;
    if (!r.ok) { $("asset-errors").textContent = await problems(r); return; }
    e.target.reset();
    await loadAssets();
  });

  $("build-button").addEventListener("click", async () => {
    const r = await api(assetsUrl(assetsSlug, "/build"), { method: "POST" });
    if (!r.ok) { $("asset-errors").textContent = await problems(r); return; }
    showBuild(await r.json());
  });

  $("edit-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const slug = e.target.dataset.slug;
    const texts = Object.fromEntries(new FormData(e.target));
    const r = await api(`/studies/${encodeURIComponent(slug)}`, {
      method: "PATCH", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ texts }) });
    if (!r.ok) { $("edit-errors").textContent = await problems(r); return; }
    $("edit-panel").hidden = true;
    await refresh();
  });

  $("create-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const file = $("create-file").files[0];
    if (!file) return;
    const r = await api("/studies/file", { method: "POST", headers: { "Content-Type": "application/toml" },
                                           body: await file.text() });
    $("create-errors").textContent = r.ok ? "" : await problems(r);
    if (!r.ok) return;
    // 202: the study file gives its clips ([clips]); the build job makes them: show its progress
    const building = r.status === 202 ? (await r.json()).study.slug : null;
    e.target.reset();
    await refresh();
    if (building) await showAssets(building);
  });

  namePattern();
  Researcher.start(refresh, () => { $("studies").hidden = true; });
})();
