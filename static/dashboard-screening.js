// The dashboard's screening and pilot panel (issue 28): the statistics with and without the study's screening
// rules side by side, the excluded participants with the rules that flagged them and by how much, the subject
// model (P.910/P.913) per comparison and participant, and the pilot runs (preview link, include, delete).
"use strict";

window.DashboardScreening = (() => {
  const $ = (id) => document.getElementById(id);
  const fmt = (v, digits = 2) => Researcher.number(v, digits);
  const p = (v) => (v === null || v === undefined ? "–" : v < 0.001 ? "< 0.001" : v.toFixed(3));
  const interval = (ci) => (ci && ci[0] !== null ? `${fmt(ci[0])} … ${fmt(ci[1])}` : "–");
  const short = (sid) => sid.slice(0, 8);
  const RULE_NAMES = {
    catch: "failed catch trials", straight_lining: "answer variance", z_outlier: "share of |z| outlier votes",
    bt500: "BT.500 (P+Q)/(J·R)", correlation: "correlation with the panel",
    disagreement: "variance of the differences from the others", fast: "share answered before one playback",
  };
  const pct = (v) => (v === null || v === undefined ? "–" : `${(100 * v).toFixed(v < 0.01 && v > 0 ? 2 : 0)} %`);

  // The design calibration (docs/screening.md): each rule's threshold, how many simulated good observers it
  // flags, its power against random, straight-lining and inverted ones, and the rules the design is too small for.
  function renderCalibration(s) {
    const c = s.calibration;
    if (!c) {
      $("calibration-note").textContent = s.too_little_data && s.too_little_data.length
        ? `Too little data to judge: ${s.too_little_data.join(", ")}.` : "Fixed thresholds (the standards' values).";
      $("table-calibration").replaceChildren();
      return;
    }
    const g = c.good_observers;
    $("calibration-note").textContent = (c.planned ? "Planned (nobody has finished yet): " : "") +
      `${c.panels} simulated panels of ${c.participants} participants, good observers ${g.source === "fitted"
        ? "fitted to this study's votes" : "from the prior (too few finished participants to fit)"}; ` +
      `false-flag rate ${pct(c.false_flag_rate_per_rule)} per rule (${c.seconds.toFixed(2)} s, seed ${c.seed}).` +
      (s.too_little_data.length ? ` Too little data for this design: ${s.too_little_data.join(", ")}.` : "");
    Researcher.fillTable($("table-calibration"),
      ["rule", "threshold", "good flagged", "random", "straight-lining", "inverted", "verdict"],
      Object.entries(c.rules).map(([rule, r]) => [
        rule, r.threshold === null ? "–" : `${r.flagged_when} ${fmt(r.threshold)}`, pct(r.false_flag),
        pct(r.power.random), pct(r.power.straight), pct(r.power.inverted),
        r.judged ? "judges" : `too little data: ${r.reason.replace(/^too little data for this design: /, "")}`]));
  }

  function render(res) {
    const s = res.screening;
    if (!s) return;
    const flagged = Object.entries(s.flagged).map(([rule, n]) => `${rule} ${n}`).join(", ") || "none";
    $("screening-summary").textContent =
      `Rules: ${s.rules.join(", ")}. Flagged per rule: ${flagged}. Screened out: ${res.participants.screened_out} ` +
      `of ${res.participants.completed} who finished.`;
    const without = new Map(res.without_screening.comparisons.map((c) => [`${c.animation}|${c.condition}`, c]));
    const rows = res.comparisons.map((c) => {
      const w = without.get(`${c.animation}|${c.condition}`) || {};
      return [`${c.animation}, ${c.condition}`, c.n_participants, fmt(c.mean_score), interval(c.ci95), p(c.p_holm),
              w.n_participants ?? "–", fmt(w.mean_score), interval(w.ci95), p(w.p_holm)];
    });
    const o = res.overall, wo = res.without_screening.overall;
    rows.push(["all comparisons", o.n_participants, fmt(o.mean_score), interval(o.ci95), p(o.wilcoxon_p),
               wo.n_participants, fmt(wo.mean_score), interval(wo.ci95), p(wo.wilcoxon_p)]);
    Researcher.fillTable($("table-screening"), ["comparison", "n (screened)", "mean", "95 % CI", "Holm p", "n (everyone)", "mean",
                                 "95 % CI", "Holm p"], rows);
    Researcher.fillTable($("table-excluded"), ["participant", "screened by", "measures (value / threshold)"],
          s.excluded.map((e) => [short(e.session_id), e.screened_by.join(", "),
                                 Object.entries(e.rules).filter(([, r]) => r.flagged)
                                   .map(([rule, r]) => `${RULE_NAMES[rule] || rule}: ${fmt(r.value)} / ${fmt(r.threshold)}`)
                                   .join("; ")]));
    $("excluded-empty").hidden = s.excluded.length > 0;
    renderCalibration(s);
    const m = res.subject_model;
    if (m && m.comparisons) {
      Researcher.fillTable($("table-subject-comparisons"), ["comparison", "modelled score", "95 % CI"],
            m.comparisons.map((c) => [`${c.animation}, ${c.condition}`, fmt(c.score), interval(c.ci95)]));
      Researcher.fillTable($("table-subject-participants"), ["participant", "bias", "95 % CI", "inconsistency", "95 % CI"],
            m.participants.map((q) => [short(q.session_id), fmt(q.bias), interval(q.bias_ci95), fmt(q.inconsistency),
                                       interval(q.inconsistency_ci95)]));
      $("subject-model-note").textContent = m.note || `Maximum likelihood, ${m.iterations} iterations (${m.status}).`;
    } else {
      $("table-subject-comparisons").replaceChildren();
      $("table-subject-participants").replaceChildren();
      $("subject-model-note").textContent = m ? m.note : "";
    }
    $("pilot-count").textContent = `${res.participants.pilot} pilot session(s)` +
      (res.pilot_included ? ", included in everything above." : ", left out of everything above.");
  }

  // `slug()`: the study shown; `refresh()`: reloads the results.
  function start(slug, refresh) {
    $("include-pilot").addEventListener("change", () => refresh());
    $("preview-link").addEventListener("click", async () => {
      const r = await Researcher.api(`/studies/${encodeURIComponent(slug())}/preview`, { method: "POST" });
      const body = await r.json().catch(() => ({}));
      if (!r.ok) { $("pilot-message").textContent = body.detail || `HTTP ${r.status}`; return; }
      const link = Object.assign(document.createElement("a"), { href: body.url, target: "_blank", rel: "noopener",
                                                                textContent: `${location.origin}${body.url}` });
      $("pilot-message").replaceChildren("Preview link (until ", body.expires_at.slice(0, 10), "): ", link);
    });
    $("delete-pilot").addEventListener("click", async () => {
      if (!confirm("Delete every pilot session of this study, with all its answers?")) return;
      const r = await Researcher.api(`/studies/${encodeURIComponent(slug())}/pilot-sessions`, { method: "DELETE" });
      const body = await r.json().catch(() => ({}));
      $("pilot-message").textContent = r.ok ? `Deleted ${body.sessions} pilot session(s) and ${body.votes} vote(s).`
                                            : `Delete failed (HTTP ${r.status}).`;
      await refresh();
    });
  }

  const query = () => ($("include-pilot").checked ? "?pilot=true" : "");
  return { render, start, query };
})();
