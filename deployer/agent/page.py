"""``GET /``: the agent's live page. The run-report page's look (deployer/pages/assets.CSS); the page itself holds
no data: its script fetches /v1 (with the token the user gives it, kept in the tab's sessionStorage) every few
seconds and builds the tables with textContent only, so a device's name is always text, never markup.

The Content-Security-Policy allows exactly this page's own script and style (by their SHA-256) and requests to
the agent itself: nothing from anywhere else, no inline handler, no frame around it.
"""

from __future__ import annotations

import base64
import hashlib

from aiohttp import web

from ..pages.assets import CSS as REPORT_CSS

CSS = (
    REPORT_CSS
    + """
header .where { color: var(--muted); } #state { margin: .2rem 0 .6rem; }
td.drift-none { color: var(--muted); }
.st-owned, .st-ok { color: var(--ok); }
.st-drifted, .st-replaced, .st-not-owned, .st-restore-failed, .st-unknown { color: var(--warn); }
.st-running { color: #0969da; }
td.name, td.time { white-space: nowrap; }
form.token { margin: 1rem 0; display: flex; gap: .5rem; } form.token input { font: inherit; min-width: 24rem; }
"""
)

JS = r"""
"use strict";
(function () {
  var KEY = "deployer-agent-token", EVERY = 5000, rounds = 0;
  var m = /(?:^#|&)token=([^&]*)/.exec(location.hash);
  if (m) {  // a token in the fragment (never sent to a server): kept for this tab, then taken out of the address
    try { sessionStorage.setItem(KEY, decodeURIComponent(m[1])); } catch (e) { /* storage off: ask below */ }
    history.replaceState(null, "", location.pathname + location.search);
  }
  function token() { try { return sessionStorage.getItem(KEY); } catch (e) { return null; } }
  function el(tag, attrs, kids) {
    var e = document.createElement(tag);
    Object.keys(attrs || {}).forEach(function (k) { e.setAttribute(k, attrs[k]); });
    (kids || []).forEach(function (k) {
      if (k === null || k === undefined) return;
      e.appendChild(typeof k === "object" ? k : document.createTextNode(String(k)));
    });
    return e;
  }
  function name(text) { return el("bdi", {}, [text]); }  // a name never turns the text around it
  function get(path) {
    var h = {"Accept": "application/json"}, t = token();
    if (t) h["Authorization"] = "Bearer " + t;
    return fetch(path, {headers: h, cache: "no-store", credentials: "omit"}).then(function (r) {
      return r.json().then(function (b) { if (!r.ok) throw {status: r.status, body: b}; return b; });
    });
  }
  function table(id, heads, rows, empty) {
    var box = document.getElementById(id);
    box.replaceChildren();
    if (!rows.length) { box.appendChild(el("p", {"class": "notice"}, [empty])); return; }
    var head = el("tr", {}, heads.map(function (h) { return el("th", {}, [h]); }));
    box.appendChild(el("table", {}, [el("thead", {}, [head]), el("tbody", {}, rows)]));
  }
  function cell(text, cls) { return el("td", cls ? {"class": cls} : {}, [text]); }
  function value(v) { return v === null || v === undefined ? "unreadable" : String(v); }
  function render(agent, devices, windows, pending, events) {
    var where = document.getElementById("where");
    where.replaceChildren(name(agent.url), " \u00b7 ", name(agent.inventory), " \u00b7 deployer " + agent.version +
      " \u00b7 PID " + agent.pid + " \u00b7 auth " + agent.auth,
      agent.you && agent.you.user ? " \u00b7 you: " : "", agent.you && agent.you.user ? name(agent.you.user) : "");
    var counts = {};
    devices.forEach(function (d) { var s = d.drifted ? "drifted" : d.status; counts[s] = (counts[s] || 0) + 1; });
    var cbox = document.getElementById("counts");
    cbox.replaceChildren();
    Object.keys(counts).sort().forEach(function (s) {
      cbox.appendChild(el("span", {"class": "count", "data-status": s}, [el("b", {}, [counts[s]]), s]));
    });
    var win = {};
    windows.forEach(function (w) { w.devices.forEach(function (n) { win[n] = w; }); });
    table("devices", ["device", "status", "drift", "pending", "window", "last check", "writes", "address"],
      devices.map(function (d) {
        var drift = d.drift.map(function (p) {
          return p.name + " is " + value(p.device) + " (adopted " + p.adopted + ")";
        });
        var w = win[d.name];
        var why = d.unreachable || d.not_owned || "";
        var st = d.drifted ? "drifted" : d.status;
        return el("tr", {"class": "dev", "data-device": d.name, "data-status": d.status,
                         "data-drifted": String(d.drifted)}, [
          el("td", {"class": "name"}, [name(d.name)]),
          el("td", {"class": "st st-" + st, "title": why}, [d.status + (why ? " - " + why : "")]),
          cell(drift.length ? drift.join("; ") : "none", drift.length ? "drift" : "drift-none"),
          cell(d.pending ? d.pending + " pending" : "none", "num"),
          cell(w ? w.kind + " until " + w.deadline : ""),
          cell(d.last_check || "never", "time"),
          cell(d.writes, "num"),
          el("td", {}, [name(d.url + " unit " + d.unit)])]);
      }), "no devices in the inventory");
    table("windows", ["run", "kind", "devices", "deadline", "seconds left"], windows.map(function (w) {
      return el("tr", {"data-run": w.run}, [cell(w.run), cell(w.kind), el("td", {}, w.devices.map(function (n, i) {
        return el("span", {}, [i ? ", " : "", name(n)]);
      })), cell(w.deadline), cell(Math.round(w.seconds_left), "num")]);
    }), "no soak or confirm window is open");
    var prows = [];
    pending.devices.forEach(function (d) {
      d.changes.forEach(function (c) {
        prows.push(el("tr", {"data-device": d.name}, [el("td", {}, [name(d.name)]), el("td", {}, [name(c.name)]),
          cell(c.adopted === null ? "(not adopted)" : c.adopted),
          cell(c.files === null ? "(not in the files)" : c.files)]));
      });
    });
    table("pending", ["device", "parameter", "adopted", "in the files"], prows,
      "the files hold the adopted state: nothing pending");
    var problems = document.getElementById("problems");
    problems.replaceChildren();
    (pending.problems ? [].concat(pending.problems) : []).forEach(function (p) {
      problems.appendChild(el("p", {"class": "error"}, [typeof p === "string" ? p : JSON.stringify(p)]));
    });
    table("events", ["time", "device", "kind", "message"], events.slice().reverse().map(function (e) {
      return el("tr", {"data-kind": e.kind}, [cell(e.time, "time"),
        el("td", {"class": "name"}, [e.device === null ? "" : name(e.device)]),
        cell(e.kind, "st st-" + e.kind), el("td", {}, [name(e.message)])]);
    }), "no events");
  }
  function ask() {
    var box = document.getElementById("state");
    var input = el("input", {"type": "password", "autocomplete": "off", "placeholder": "the agent's token"});
    var form = el("form", {"class": "token"}, [input, el("button", {"type": "submit"}, ["show"])]);
    form.addEventListener("submit", function (ev) {
      ev.preventDefault();
      try { sessionStorage.setItem(KEY, input.value.trim()); } catch (e) { /* nothing to keep it in */ }
      refresh();
    });
    box.replaceChildren(el("p", {"class": "error"}, ["this agent needs its token (kept in this tab only)"]), form);
  }
  var timer = null;
  function refresh() {
    if (timer !== null) { clearTimeout(timer); timer = null; }
    Promise.all([get("/v1/agent"), get("/v1/devices"), get("/v1/windows"), get("/v1/pending"),
                 get("/v1/events?limit=30")])
      .then(function (a) {
        render(a[0], a[1].devices, a[2].windows, a[3], a[4].events);
        document.getElementById("state").replaceChildren(el("span", {"class": "notice"},
          ["updated " + new Date().toLocaleTimeString() + ", every " + EVERY / 1000 + " s"]));
        timer = setTimeout(refresh, EVERY);
      }, function (e) {
        if (e && e.status === 401) { ask(); }
        else {
          var why = e && e.body && e.body.error ? e.body.error.message : String(e && e.message || e);
          document.getElementById("state").replaceChildren(
            el("p", {"class": "error"}, ["cannot read the agent: " + why]));
          timer = setTimeout(refresh, EVERY);
        }
      }).then(function () { document.body.setAttribute("data-ready", String(++rounds)); });
  }
  refresh();
})();
"""


def _sha(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


HTML = (
    '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
    '<meta name="viewport" content="width=device-width, initial-scale=1">'
    f"<title>deployer agent</title><style>{CSS}</style></head><body>"
    '<header><h1>deployer agent</h1><div class="where" id="where"></div></header><main>'
    '<div id="state"><p class="notice">reading the agent ...</p></div>'
    '<div class="counts" id="counts"></div>'
    '<h2>Devices</h2><div id="devices"></div><h2>Open windows</h2><div id="windows"></div>'
    '<h2>Pending changes of the files</h2><div id="problems"></div><div id="pending"></div>'
    '<h2>Last events</h2><div id="events"></div>'
    f"</main><script>{JS}</script></body></html>"
)

CSP = (
    f"default-src 'none'; script-src {_sha(JS)}; style-src {_sha(CSS)}; connect-src 'self'; img-src 'self' data:; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
HEADERS = {
    "Content-Type": "text/html; charset=utf-8",
    "Content-Security-Policy": CSP,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "X-Frame-Options": "DENY",
    "Cache-Control": "no-store",
}


async def page(request: web.Request) -> web.Response:
    """The page's shell: the same bytes for everybody (no data, no token needed; docs/operations.md)."""
    return web.Response(text=HTML, headers=HEADERS)
