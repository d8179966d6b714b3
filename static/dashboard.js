// The researcher dashboard: log in, watch progress, read the statistics, export.  Polls the results every 15 s.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const params = new URLSearchParams(location.search);
  let slug = params.get("study"); // none: the first study the researcher may see
  // Scores are from the test condition's point of view; the labels name the study's reference.  The scores come
  // from the API (results.answer_scale, server/studies/scale.py): -max is the reference much better, +max the test.
  const SCORE_COLOURS = { strong: ["#b2182b", "#2166ac"], weak: ["#ef8a62", "#67a9cf"], none: "#cfcfcf" };
  const scoreLegend = (ref, scale) => scale.scores.map((s) => {
    const strength = Math.abs(s) === scale.max ? "significantly" : "slightly";
    if (s === 0) return { key: "0", label: "equal", color: SCORE_COLOURS.none };
    const colours = Math.abs(s) === scale.max ? SCORE_COLOURS.strong : SCORE_COLOURS.weak;
    return { key: String(s), label: `${s < 0 ? ref : "test"} ${strength} better`, color: colours[s < 0 ? 0 : 1] };
  });
  // Enough distinct colours for any number of answers or conditions (cycled, then lightened).
  const PALETTE = ["#2166ac", "#ef8a62", "#4d9221", "#762a83", "#b2182b", "#67a9cf", "#e08214", "#9e9e9e"];
  const colour = (i) => PALETTE[i % PALETTE.length];
  let results = null;
  let timer = null;

  const label = (c) => `${c.animation}, ${c.condition}`;
  const fmt = (v, digits = 3) => Researcher.number(v, digits);
  // A condition without a finite scale value (ranking status "separated"): which way it runs off, if known.
  const unbounded = (bound) => (bound ? `no finite value (${bound} the reference)` : "–");
  const p = (v) => (v === null || v === undefined ? "–" : v < 0.001 ? "< 0.001" : v.toFixed(3));

  const api = Researcher.api;

  async function open() {
    $("login").hidden = true;
    await refresh();
    clearInterval(timer);
    timer = setInterval(() => refresh().catch(() => {}), 15000);
  }

  async function refresh() {
    if (!slug) {
      const list = await api("/studies");
      const studies = list.ok ? await list.json() : [];
      if (!studies.length) { location.href = "/dashboard/studies"; return; }
      slug = studies[0].slug;
    }
    $("participant-link").href = `/s/${encodeURIComponent(slug)}`;
    const r = await api(`/studies/${encodeURIComponent(slug)}/results${DashboardScreening.query()}`);
    if (!r.ok) { $("status").textContent = `Cannot load the results (HTTP ${r.status}).`; return; }
    results = await r.json();
    render(results);
    $("status").textContent = `Updated ${new Date().toLocaleTimeString()}`;
  }

  function card(value, text) {
    const div = document.createElement("div");
    div.className = "card";
    div.innerHTML = `<div class="value"></div><div class="label"></div>`;
    div.querySelector(".value").textContent = value;
    div.querySelector(".label").textContent = text;
    return div;
  }

  function render(res) {
    $("dashboard").hidden = false;
    $("actions").hidden = false;
    const o = res.overview;
    $("title").textContent = `${o.title} — ${o.slug}`;
    $("state-badge").textContent = o.state;
    $("state-badge").className = `badge ${o.state}`;
    $("toggle-state").textContent = o.state === "open" ? "Close study" : "Open study";
    const n = res.participants;
    const minutes = o.median_completion_s === null ? "–" : `${(o.median_completion_s / 60).toFixed(1)} min`;
    $("overview").replaceChildren(card(n.started, "started"), card(n.completed, "completed"),
                                  card(n.screened_out, "screened out (not analysed)"),
                                  card(n.withdrawn, "withdrawn"), card(n.active, "in progress"),
                                  card(o.votes, "votes"), card(minutes, "median completion time"));
    const comps = res.comparisons;
    const ref = o.reference;
    document.querySelectorAll(".reference-name").forEach((el) => { el.textContent = ref; });
    $("chart-distribution").replaceChildren(Charts.diverging(
      comps.map((c) => ({ label: label(c), counts: c.counts })), scoreLegend(ref, res.answer_scale), "Answers per comparison"));
    $("chart-thesis").replaceChildren(Charts.stacked(
      comps.map((c) => ({ label: label(c), positive: c.positive, negative: c.negative })),
      [{ key: "positive", label: "positive", color: "#4d9221" }, { key: "negative", label: "negative", color: "#c51b7d" }],
      "Thesis grouping"));
    $("chart-split").replaceChildren(Charts.stacked(
      comps.map((c) => ({ label: label(c), test: c.test_better, equal: c.equal, reference: c.reference_better })),
      [{ key: "test", label: "test better", color: "#2166ac" }, { key: "equal", label: "equal", color: "#cfcfcf" },
       { key: "reference", label: `${ref} better`, color: "#b2182b" }], "Neutral split"));
    $("chart-means").replaceChildren(Charts.forest(
      [...comps.map((c) => ({ label: label(c), value: c.mean_score, ci: c.ci95 })),
       { label: "all comparisons", value: res.overall.mean_score, ci: res.overall.ci95 }], res.answer_scale.min, res.answer_scale.max,
      "Mean preference"));
    Researcher.fillTable($("table-stats"), ["comparison", "n", "mean", "95 % CI", "Wilcoxon p", "Holm p", "sign test p",
                             "rank-biserial", "n for 80 % power"],
          comps.map((c) => [label(c), c.n_participants, fmt(c.mean_score, 2),
                            c.ci95 ? `${fmt(c.ci95[0], 2)} … ${fmt(c.ci95[1], 2)}` : "–", p(c.wilcoxon_p), p(c.p_holm),
                            p(c.sign_test_p), fmt(c.rank_biserial, 2), c.participants_for_80_power ?? "–"]));
    const sc = res.swap_consistency;
    $("stats-notes").textContent =
      `Side bias (mean raw answer, left = +2): ${fmt(res.side_bias.mean, 2)} (Wilcoxon p ${p(res.side_bias.p)}). ` +
      `Consistency of the two side-swapped showings: weighted κ ${fmt(sc.weighted_kappa, 2)}, exact agreement ` +
      `${fmt(sc.exact_agreement, 2)}, within one step ${fmt(sc.within_one, 2)} (${sc.pairs} pairs). ` +
      `Krippendorff's α (ordinal): ${fmt(res.krippendorff_alpha_ordinal, 2)}. ${res.methods.wilcoxon}.`;
    Researcher.fillTable($("table-ranking"), ["animation", "condition", "scale value", "95 % CI", "votes", "fit"],
          (res.rankings || []).flatMap((r) => r.conditions.map((c) => [
            r.animation, c.condition, c.value == null ? unbounded(c.bound) : fmt(c.value, 2),
            c.ci95 ? `${fmt(c.ci95[0], 2)} … ${fmt(c.ci95[1], 2)}` : "–", c.votes, r.fit.status])));
    renderScale(res);
    renderThresholds(res.thresholds);
    renderQuestions(res, comps);
    // The clips of the study's stimulus set, with the metrics they had when it was made (pinned when it opened).
    $("stimulus-set").textContent = res.stimulus_set
      ? `The study's stimulus set ${res.stimulus_set.slice(0, 12)}: its clips as they were when the set was made ` +
        `(pinned when the study opened; exports name it in the column stimulus_set).`
      : "";
    DashboardScreening.render(res);
    renderMetrics(res.clips);
    renderBenchmark(res.benchmark);
  }

  // One scale per animation (every design mode), its P(better) and pair-count matrices, and for adaptive designs
  // the information each round promised.
  function renderScale(res) {
    const scales = res.scale || [];
    const rows = scales.flatMap((s) => s.conditions.map((c, i) => ({
      label: `${s.animation}, ${c}`, value: s.value[i], ci: s.ci95[i], missing: s.bound[i] ? unbounded(s.bound[i]) : null })));
    // The axis spans what is drawn: a row without a value shows its text only, not its bootstrap interval.
    const values = rows.filter((r) => r.value !== null && r.value !== undefined).flatMap((r) => (r.ci ? r.ci : [r.value]));
    const lo = Math.floor(Math.min(0, ...values) * 2) / 2, hi = Math.ceil(Math.max(0, ...values) * 2) / 2;
    $("chart-scale").replaceChildren(Charts.forest(rows, lo, Math.max(hi, lo + 0.5), "Scale per animation"));
    Researcher.fillTable($("table-scale"), ["animation", "condition", "scale value", "95 % CI", "JND", "participants", "fit"],
          scales.flatMap((s) => s.conditions.map((c, i) => [
            s.animation, c, s.value[i] == null ? unbounded(s.bound[i]) : fmt(s.value[i], 2), s.ci95[i] ? `${fmt(s.ci95[i][0], 2)} … ${fmt(s.ci95[i][1], 2)}` : "–",
            fmt(s.value_jnd[i], 2), s.participants, s.status])));
    const matrix = (cell) => scales.flatMap((s) => s.conditions.map((c, i) => [
      `${s.animation}, ${c}`, ...s.conditions.map((_, j) => cell(s, i, j))]));
    const width = Math.max(0, ...scales.map((s) => s.conditions.length));
    const header = ["", ...Array.from({ length: width }, (_, j) => scales[0] ? (scales[0].conditions[j] ?? "") : "")];
    Researcher.fillTable($("table-pbetter"), header, matrix((s, i, j) => {
      const v = s.p_better[i][j];
      return v === null || v === undefined ? "–" : `${v.toFixed(2)}${v < 0.025 || v > 0.975 ? " *" : ""}`;
    }));
    Researcher.fillTable($("table-pairs"), header, matrix((s, i, j) => (i === j ? "–" : String(s.pair_counts[i][j]))));
    const rounds = res.adaptive_rounds;
    $("adaptive-panel").hidden = !rounds;
    if (!rounds) return;
    const animations = rounds.length ? Object.keys(rounds[0].information) : [];
    if (rounds.length) {
      $("chart-rounds").replaceChildren(Charts.lines(animations.map((a, k) => ({
        label: a, color: colour(k), points: rounds.map((r) => [r.round, r.information[a]]) })),
        "Information per round", "round (participant)", "nats"));
    } else {
      $("chart-rounds").replaceChildren();
    }
    Researcher.fillTable($("table-rounds"), ["round", "votes before", ...animations.map((a) => `${a}: nats`),
                              ...animations.map((a) => `${a}: pairs`)],
          rounds.map((r) => [r.round, r.votes_before, ...animations.map((a) => fmt(r.information[a], 3)),
                             ...animations.map((a) => r.pairs[a].map((p) => p.join("–")).join(", "))]));
  }

  // Threshold designs (issue 38): each animation's threshold, its cheapest indistinguishable level and the frontier
  // plot the server draws (an SVG document parsed as such, never as HTML).
  function renderThresholds(t) {
    $("thresholds-panel").hidden = !t;
    if (!t) return;
    const animations = t.animations || [];
    const interval = (i) => (i ? `${fmt(i.estimate, 1)} (${fmt(i.low, 1)} … ${fmt(i.high, 1)})` : "–");
    $("thresholds-summary").textContent = t.note || animations.map((a) => {
      if (a.error) return `${a.animation}: ${a.error}.`;
      const c = a.cheapest_indistinguishable;
      const fit = a.fit ? `threshold ${interval(a.fit.threshold_profile || a.fit.threshold)} ${t.ladder}` : "no fit";
      return `${a.animation}: ${fit}; cheapest indistinguishable: ` +
        (c ? `${c.condition} (${fmt(c.cost, 3)} ${t.cost_metric})` : "none yet");
    }).join(" ");
    const doc = new DOMParser().parseFromString(t.svg || "<svg xmlns='http://www.w3.org/2000/svg'/>", "image/svg+xml");
    $("chart-frontier").replaceChildren(document.importNode(doc.documentElement, true));
    Researcher.fillTable($("table-thresholds"), ["animation", "condition", "level", "cost", "answers", "correct",
                             "95 % CI", "Pareto", "indistinguishable"],
          animations.filter((a) => !a.error).flatMap((a) => a.points.map((q) => [
            a.animation, q.condition, fmt(q.level, 1), fmt(q.cost, 3), q.detection.trials,
            fmt(q.detection.p, 2), `${fmt(q.detection.low, 2)} … ${fmt(q.detection.high, 2)}`,
            q.pareto ? "yes" : "", q.indistinguishable ? "yes" : ""])));
  }

  // One panel per question of the study: the mean score of each comparison for each answer.
  function renderQuestions(res, comps) {
    const box = $("question-panels");
    box.replaceChildren();
    for (const q of res.overview.questions) {
      if (q.type === "text") continue; // free text has no groups to compare
      const groups = res.demographics[q.id] || {};
      const rows = comps.map((c) => {
        const key = `${c.animation}-${c.condition}`;
        const values = {};
        for (const [answer, g] of Object.entries(groups)) values[answer] = g.comparisons[key]?.mean_score;
        return { label: label(c), values };
      });
      const present = Object.keys(groups).map((answer, i) => ({
        key: answer, label: `${answer === "unanswered" ? "not answered" : answer} (${groups[answer].participants})`,
        color: answer === "unanswered" ? "#d9d9d9" : colour(i) }));
      const panel = document.createElement("section");
      panel.className = "panel";
      const h = document.createElement("h2");
      h.textContent = `By answer: ${q.text}`;
      const chart = document.createElement("div");
      chart.className = "chart";
      chart.id = `chart-q-${q.id}`;
      chart.append(Charts.groupedSigned(rows, present, res.answer_scale.min, res.answer_scale.max, `Mean score by ${q.id}`));
      panel.append(h, chart);
      box.append(panel);
    }
  }

  // The study's own clips (`shown`) in the chart and first in the table; the rest of the clip set below them.
  function renderMetrics(all) {
    if (!all.length) { $("chart-metrics").textContent = "This study has no stimulus set."; $("table-metrics").replaceChildren(); return; }
    const mine = all.filter((c) => c.shown);
    const clips = [...mine, ...all.filter((c) => !c.shown)];
    const charted = mine.length ? mine : all;
    const animations = [...new Set(charted.map((c) => c.animation))];
    const conditions = [...new Set(charted.map((c) => c.condition))];
    const legend = conditions.map((k, i) => ({ key: k, label: k, color: i === 0 ? "#555555" : colour(i - 1) }));
    const groups = animations.map((a) => ({
      label: `${a}: foot skate`,
      values: Object.fromEntries(charted.filter((c) => c.animation === a).map((c) => [c.condition, c.metrics.foot_skate_ratio])),
    }));
    $("chart-metrics").replaceChildren(Charts.columns(groups, legend, `Foot skate ratio per clip${mine.length ? " of this study" : ""}`,
                                                      (v) => `${Math.round(v * 100)} %`));
    const m = (c) => c.metrics;
    const name = (id) => { const c = all.find((x) => x.id === id); return c ? `${c.animation} ${c.condition}` : id; };
    Researcher.fillTable($("table-metrics"), ["clip", "in this study", "method", "same arrays as", "keys", "foot skate", "source skate", "slide mm",
                               "penetration mm", "floating mm", "MPJPE mm", "max rotation error °",
                               "key velocity jump rad/s", "key acceleration jump rad/s²", "jerk m/s³", "bytes",
                               "seam jump mm", "transition skate", "source window skate", "transition slide mm", "switch velocity jump rad/s",
                               "switch acceleration jump rad/s²", "settle s", "hips phase r (lag)", "knee phase r (lag)", "fidelity",
                               "pose error °", "bones off ° (p95)", "hip width ×", "knees forward", "worst stance mm",
                               "mirrored half ° (p95)", "head over hips m", "feet reach mm"],
          clips.map((c) => [`${c.animation} ${c.condition}`, c.shown ? "yes" : "", method(c),
                            c.identical_to ? name(c.identical_to) : "", c.key_count,
                            fmt(m(c).foot_skate_ratio, 3), fmt(m(c).source_foot_skate_ratio, 3),
                            fmt(m(c).foot_slide_mm, 1), fmt(m(c).penetration_mm, 1), fmt(m(c).floating_mm, 1),
                            fmt(m(c).mpjpe_mm, 1), fmt(m(c).max_global_error_deg, 3),
                            fmt(m(c).key_velocity_jump_rad_s, 3), fmt(m(c).key_accel_jump_rad_s2, 3),
                            fmt(m(c).jerk_mean, 1), m(c).bytes, fmt(m(c).seam_jump_mm, 1),
                            // a sequence's transitions (issue 39; "–" for any other clip)
                            fmt(m(c).transition_foot_skate_ratio, 3), fmt(m(c).source_window_foot_skate_ratio, 3),
                            fmt(m(c).transition_foot_slide_mm, 1),
                            fmt(m(c).switch_velocity_jump_rad_s, 1), fmt(m(c).switch_accel_jump_rad_s2, 0),
                            fmt(m(c).settle_s, 2),
                            phase(m(c).phase_hips_r, m(c).phase_hips_lag), phase(m(c).phase_knee_r, m(c).phase_knee_lag),
                            fidelity(m(c)), fmt(m(c).pose_error_deg, 1), fmt(m(c).bone_error_deg, 1),
                            fmt(m(c).hip_width_ratio, 2),
                            m(c).knees_forward == null ? "–" : `${Math.round(m(c).knees_forward * 100)} %`,
                            m(c).landing_m == null ? "–" : fmt(m(c).landing_m * 1000, 0),
                            fmt(m(c).mirror_error_deg, 1), fmt(m(c).upright_m, 2),
                            m(c).foot_reach_m == null ? "–" : fmt(m(c).foot_reach_m * 1000, 0)]));
  }

  // The fidelity gate's verdict (docs/motion-from-the-wild.md); clip sets built before the gate have none.
  function fidelity(metrics) {
    if (metrics.unfaithful == null) return "–";
    return metrics.unfaithful ? "UNFAITHFUL (built anyway)" : "ok";
  }

  // The registered method and its parameters, e.g. "quantized (bits 12, reduced_epsilon_deg 2)".
  function method(c) {
    const params = Object.entries(c.params || {}).filter(([, v]) => v !== null).map(([k, v]) => `${k} ${v}`).join(", ");
    return params ? `${c.method} (${params})` : c.method;
  }

  // Hybrid against its keyframe clip: correlation at lag 0 and the best lag in frames; "–" for keyframe clips.
  function phase(r, lag) { return r == null ? "–" : `${fmt(r, 2)} (${lag > 0 ? "+" : ""}${lag})`; }

  // Performance: the keys runtime's figures (the benchmark's headline variant), runtime memory per clip and
  // variant, and per clip (every condition) its cost per frame at the largest crowd, its ratio to the keyframe
  // clip of its animation, bytes and largest error.
  function renderBenchmark(bench) {
    const box = $("chart-benchmark");
    if (!bench || !bench.series) {
      box.textContent = "No benchmark results yet (run `animstudy bench`).";
      $("chart-memory").replaceChildren();
      $("table-benchmark").replaceChildren();
      $("summary-benchmark").textContent = "";
      return;
    }
    const colors = ["#555555", "#2166ac", "#67a9cf", "#b2182b", "#4d9221", "#e08214"];
    box.replaceChildren(Charts.lines(bench.series.map((s, i) => ({ label: s.name, color: colors[i % colors.length], points: s.points })),
                                     "Pose evaluation time (animstudy bench)", bench.x_label || "characters", bench.y_label || "ms per frame"));
    const memory = bench.memory || [];
    const clips = [...new Set(memory.map((m) => m.clip))];
    const variants = ["keys", "baked", "reference"].filter((v) => memory.some((m) => m.variant === v));
    const series = [{ key: "stored", label: "stored keys", color: colors[0] },
                    ...variants.map((v, i) => ({ key: v, label: v, color: colors[i + 1] }))];
    const bytes = (clip, v) => memory.find((m) => m.clip === clip && m.variant === v);
    $("chart-memory").replaceChildren(Charts.columns(
      clips.map((c) => ({ label: ((m) => `${m.animation} ${m.condition}`)(memory.find((x) => x.clip === c)),
                          values: Object.fromEntries([["stored", memory.find((m) => m.clip === c).stored_bytes],
                                                      ...variants.map((v) => [v, bytes(c, v)?.runtime_bytes])]) })),
      series, "Runtime bytes per clip and variant", (v) => `${(v / 1000).toFixed(1)} kB`));
    const s = bench.summary || {};
    const ratios = (s.ratios || []).filter((r) => r.characters >= 10);
    const error = (clip) => (bench.accuracy || []).find((a) => a.clip === clip && a.variant === "keys");
    const perFrame = (bench.results || []).filter((r) => r.stage === "pose" && r.variant === "keys" && r.threads === 1);
    const largest = Math.max(0, ...perFrame.map((r) => r.characters));
    Researcher.fillTable($("table-benchmark"), ["clip", `ms per frame (keys, ${largest} characters)`,
                                 "÷ keyframe (keys, ≥ 10 characters, worst)", "runtime bytes (keys)",
                                 "runtime bytes (baked)", "largest error ° (keys)"],
          clips.map((c) => {
            const m = memory.find((x) => x.clip === c && x.variant === "keys") || {};
            const mine = ratios.filter((r) => r.animation === m.animation && r.condition === m.condition).map((r) => r.ratio);
            const ms = perFrame.find((r) => r.characters === largest && r.animation === m.animation && r.condition === m.condition);
            return [c, ms ? fmt(ms.median_ms, 3) : "–", m.method === "keyframe" ? "1 (base)" : mine.length ? fmt(Math.max(...mine), 2) : "–",
                    m.runtime_bytes ?? "–", bytes(c, "baked")?.runtime_bytes ?? "–", fmt(error(c)?.max_error_deg, 3)];
          }));
    $("summary-benchmark").textContent =
      `keys runtime: worst hybrid / keyframe ${fmt(s.max_ratio_at_10_or_more, 2)} (median ${fmt(s.median_ratio_at_10_or_more, 2)}); ` +
      `${s.largest_crowd} characters ${fmt(s.largest_crowd_worst_ms, 2)} ms per frame` +
      (s.parallel_speedup_median == null ? "" : `, ${s.parallel_threads} threads ${fmt(s.parallel_speedup_median, 2)}× as fast`) +
      `; increment-0 hybrid memory ≤ ${fmt(s.max_memory_ratio_increment_0, 2)} of the keyframe clip's; ` +
      `largest hybrid error ${fmt(s.max_hybrid_error_deg, 3)}°.`;
  }

  $("toggle-state").addEventListener("click", async () => {
    const action = results?.overview.state === "open" ? "close" : "open";
    const r = await api(`/studies/${encodeURIComponent(slug)}/${action}`, { method: "POST" });
    if (r.ok) await refresh();
  });

  async function download(kind) {
    const r = await api(`/studies/${encodeURIComponent(slug)}/export.${kind}`);
    if (!r.ok) { $("status").textContent = `Export failed (HTTP ${r.status}).`; return; }
    const url = URL.createObjectURL(await r.blob());
    const a = document.createElement("a");
    a.href = url;
    a.download = `${slug}-votes.${kind}`;
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 1000);
  }
  $("export-csv").addEventListener("click", () => download("csv"));
  $("export-json").addEventListener("click", () => download("json"));
  $("export-sureal").addEventListener("click", () => download("sureal.json"));
  $("export-pwcmp").addEventListener("click", () => download("pwcmp.csv"));
  DashboardScreening.start(() => slug, refresh);

  Researcher.start(open, () => { clearInterval(timer); $("dashboard").hidden = true; });
})();
