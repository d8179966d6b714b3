// The studies page of the dashboard: every study the researcher may manage, with state and counts; create one
// from a study file, edit its texts while allowed, open and close, links to its participant page and results.
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

  async function refresh() {
    $("login").hidden = true;
    const r = await api("/studies");
    if (!r.ok) { $("status").textContent = `Cannot load the studies (HTTP ${r.status}).`; return; }
    const studies = await r.json();
    $("studies").hidden = false;
    $("actions").hidden = false;
    const t = document.createElement("table");
    const head = t.createTHead().insertRow();
    for (const h of ["study", "title", "state", "started", "completed", "votes", "trials", "links", "actions"]) {
      const th = document.createElement("th");
      th.textContent = h;
      head.appendChild(th);
    }
    const body = t.createTBody();
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
    if (r.ok) { e.target.reset(); await refresh(); }
  });

  Researcher.start(refresh, () => { $("studies").hidden = true; });
})();
