// The researcher's login, shared by the dashboard pages (results and studies): the token kept in sessionStorage,
// the page's login form (#login, #login-form, #login-error) and logout button (#logout, in #actions), and API
// calls that carry the token (an expired login shows the form again).
"use strict";

window.Researcher = (() => {
  const TOKEN = "animstudy:researcher-token";
  const $ = (id) => document.getElementById(id);
  let token = sessionStorage.getItem(TOKEN);
  let closed = () => {};

  function logout(message) {
    token = null;
    sessionStorage.removeItem(TOKEN);
    closed();
    $("actions").hidden = true;
    $("login").hidden = false;
    $("login-error").textContent = message || "";
  }

  async function api(path, options = {}) {
    const headers = { ...(options.headers || {}), Authorization: `Bearer ${token}` };
    const r = await fetch(`/api/v1${path}`, { ...options, headers, cache: "no-store" });
    if (r.status === 401) { logout("Your login has expired; please log in again."); throw new Error("unauthorized"); }
    return r;
  }

  // `opened`: shows the page's content after a login (at once when a login is stored); `onClosed`: hides it.
  function start(opened, onClosed) {
    closed = onClosed;
    $("login-form").addEventListener("submit", async (e) => {
      e.preventDefault();
      const r = await fetch("/api/v1/auth/token", { method: "POST", body: new URLSearchParams(new FormData(e.target)) });
      if (!r.ok) { $("login-error").textContent = "Wrong e-mail or password."; return; }
      token = (await r.json()).access_token;
      sessionStorage.setItem(TOKEN, token);
      await opened();
    });
    $("logout").addEventListener("click", () => logout());
    if (token) opened().catch(() => {}); else $("login").hidden = false;
  }

  // A table with a header row of `headers`; rows go into the returned body.
  function newTable(headers) {
    const table = document.createElement("table");
    const head = table.createTHead().insertRow();
    for (const h of headers) {
      const th = document.createElement("th");
      th.textContent = h;
      head.appendChild(th);
    }
    return { table, body: table.createTBody() };
  }

  // A table of text cells in place of what ``container`` held.
  function fillTable(container, headers, rows) {
    const { table, body } = newTable(headers);
    for (const row of rows) {
      const tr = body.insertRow();
      for (const cell of row) tr.insertCell().textContent = cell;
    }
    container.replaceChildren(table);
  }

  // A number as the dashboards show it: ``digits`` decimals (a value that rounds to 0 without toFixed's "-"), a
  // dash for none, and three significant digits from 1e9 up, far beyond any figure the dashboards show, where a
  // fit that ran off reaches 1e18-1e28 (toFixed would print every digit, past 1e21 all seventeen significant ones).
  function number(v, digits) {
    if (v === null || v === undefined) return "–";
    const x = Number(v);
    if (Math.abs(x) >= 1e9) return x.toPrecision(3);
    return x.toFixed(digits).replace(/^-(0\.?0*)$/, "$1");
  }

  return { api, start, newTable, fillTable, number };
})();
