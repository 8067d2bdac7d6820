"""The styles and script the pages carry inside them (no network: nothing is loaded from anywhere)."""

CSS = """
:root { --ok: #1a7f37; --bad: #b42318; --warn: #9a6700; --muted: #57606a; --line: #d0d7de; --bg: #f6f8fa; }
* { box-sizing: border-box; }
body { font: 14px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0 auto; max-width: 1400px;
       padding: 1rem 1.5rem; color: #1f2328; }
h1 { font-size: 1.5rem; margin: .2rem 0 .6rem; } h2 { font-size: 1.15rem; margin: 1.4rem 0 .5rem; }
dl.meta { display: grid; grid-template-columns: max-content 1fr; gap: .15rem 1rem; margin: 0 0 1rem; }
dl.meta dt { color: var(--muted); } dl.meta dd { margin: 0; overflow-wrap: break-word; }
.counts { display: flex; flex-wrap: wrap; gap: .5rem; margin: .5rem 0 1rem; }
.count { border: 1px solid var(--line); border-radius: 6px; padding: .35rem .7rem; background: var(--bg);
         cursor: pointer;
         font: inherit; }
.count b { font-size: 1.2rem; margin-right: .3rem; } .count.active { outline: 2px solid #0969da; }
.controls { display: flex; flex-wrap: wrap; gap: .6rem 1rem; align-items: center; margin: .5rem 0; }
.controls input[type=search] { min-width: 16rem; padding: .3rem .5rem; font: inherit; }
.controls select { font: inherit; padding: .2rem; }
table { border-collapse: collapse; width: 100%; margin: .3rem 0 .8rem; }
th, td { border-bottom: 1px solid var(--line); padding: .25rem .5rem; text-align: left; vertical-align: top; }
th { background: var(--bg); position: sticky; top: 0; }
th.sort { cursor: pointer; user-select: none; white-space: nowrap; }
th.sort[data-dir=asc]::after { content: " \\25B2"; } th.sort[data-dir=desc]::after { content: " \\25BC"; }
td.num, th.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.dev { cursor: pointer; } tr.dev:hover { background: #eaeef2; }
.st { font-weight: 600; white-space: nowrap; }
.st-ok, .st-unchanged, .st-sent { color: var(--ok); }
.st-failed, .st-partial, .st-mismatch, .st-unreachable, .st-interrupted, .st-rolled-back { color: var(--bad); }
.st-skipped, .st-unverified { color: var(--warn); }
details.device { border: 1px solid var(--line); border-radius: 6px; margin: .5rem 0; padding: .3rem .8rem; }
details.device > summary { cursor: pointer; padding: .2rem 0; }
details.device > summary .where { color: var(--muted); margin-left: .6rem; }
.notice { color: var(--muted); margin: .2rem 0; } .error { color: var(--bad); margin: .2rem 0; }
.outcome-grid { display: grid; grid-template-columns: minmax(12rem, max-content) 1fr; gap: 0 2rem; }
.outcome table.statuses { width: auto; }
.sign { display: grid; grid-template-columns: repeat(3, 1fr); gap: 2rem; margin: 2.2rem 0 .6rem; }
.sign div { border-top: 1px solid #000; padding-top: .2rem; font-size: 9pt; }
.esig table { width: auto; }
#audit { font-size: 8.5pt; } #audit td { vertical-align: top; } #audit table { margin: .1rem 0; }
#audit .digest { word-break: break-all; } #audit td:nth-child(2) { white-space: nowrap; }
.esig .digest { font-family: ui-monospace, monospace; font-size: 8.5pt; word-break: break-all; }
.identity { margin: .2rem 0; } .word { white-space: nowrap; }
.muted { color: var(--muted); } .manual { color: var(--muted); font-size: .9em; }
td.drift { background: #fff1e5; font-weight: 600; } td.same { color: var(--muted); }
td.missing { color: var(--muted); font-style: italic; }
.hidden { display: none !important; }
@media print {
  body { max-width: none; padding: 0; font-size: 10pt; }
  .controls, .counts, #devices, .noprint { display: none !important; }
  #devices.compact { display: block !important; } #devices.compact .controls { display: none !important; }
  .outcome { break-after: page; page-break-after: always; }
  dl.meta dd { overflow-wrap: break-word; word-break: normal; }
  details.device { border: none; border-top: 1px solid #000; border-radius: 0; padding: .4rem 0;
                   break-inside: avoid-page; page-break-inside: avoid; }
  details.device > summary { list-style: none; font-weight: 700; }
  details.device > summary::-webkit-details-marker { display: none; }
  th { position: static; }
  .hidden { display: none !important; }
}
"""

# One script for the three kinds of page; DATA.kind says which. Text goes into the page through esc()
# or textContent only: names and values come from devices and files.
JS = r"""
(function () {
  "use strict";
  var DATA = JSON.parse(document.getElementById("data").textContent);
  var RANK = {"failed": 0, "partial": 1, "unreachable": 2, "interrupted": 3, "rolled-back": 4, "mismatch": 5,
              "skipped": 6, "sent": 7, "ok": 8};
  function esc(s) {
    return String(s == null ? "" : s).replace(/[&<>"']/g, function (c) {
      return {"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[c];
    });
  }
  // user text inline: bidi controls balanced (an unmatched closer dropped, what is left open closed at its
  // end) and the whole in <bdi>, so a U+202E in a name cannot reorder what the page says after it
  function txt(s) {
    s = String(s == null ? "" : s);
    var open = [], out = "";
    for (var i = 0; i < s.length; i++) {
      var c = s.charCodeAt(i);
      if (c >= 0x202A && c <= 0x202E && c !== 0x202C) { open.push(0x202C); }
      else if (c >= 0x2066 && c <= 0x2068) { open.push(0x2069); }
      else if (c === 0x202C) { if (open[open.length - 1] !== c) { continue; } open.pop(); }
      else if (c === 0x2069) { var j = open.lastIndexOf(c); if (j < 0) { continue; } open.length = j; }
      out += s[i];
    }
    return "<bdi>" + esc(out + open.reverse().map(function (x) { return String.fromCharCode(x); }).join("")) +
           "</bdi>";
  }
  function st(s) { return '<span class="st st-' + esc(s) + '">' + esc(s) + "</span>"; }
  function $(id) { return document.getElementById(id); }


  // ---- a run report, and the as-found record --------------------------------------------------
  function paramTable(d) {
    var asFound = DATA.kind === "as-found";
    var h = asFound ? "<tr><th>parameter</th><th>as found</th><th>registers</th></tr>"
                    : "<tr><th>parameter</th><th>as found</th><th>desired</th><th>as left</th><th>status</th>" +
                      "<th></th></tr>";
    // the key, and beside it the parameter as the manual names it ("3-41 Ramp 1 Ramp Up Time")
    function key(p, manual) {
      return "<td>" + txt(p[0]) + (manual ? ' <span class=manual>' + txt(manual) + "</span>" : "") + "</td>";
    }
    var rows = d.params.map(function (p) {
      if (asFound) { return "<tr>" + key(p, p[3]) + "<td>" + txt(p[1]) + "</td><td class=muted>" +
                            txt(p[2]) + "</td></tr>"; }
      return "<tr>" + key(p, p[6]) + "<td>" + txt(p[1]) + "</td><td>" + txt(p[2]) + "</td><td>" +
             txt(p[3]) + "</td><td>" + st(p[4]) + "</td><td>" + txt(p[5]) + "</td></tr>";
    });
    return "<table class=params><thead>" + h + "</thead><tbody>" + rows.join("") + "</tbody></table>";
  }

  function body(d) {
    var parts = [];
    if (d.identity) { parts.push('<p class="identity">identity: ' + txt(d.identity) + "</p>"); }
    if (d.error) { parts.push('<p class="error">' + txt(d.error) + "</p>"); }
    if (d.params.length) { parts.push(paramTable(d)); }
    (d.notices || []).forEach(function (n) { parts.push('<p class="notice">note: ' + txt(n) + "</p>"); });
    if (d.commit) { parts.push('<p class="notice">commit: ' + txt(d.commit) + "</p>"); }
    if (d.snapshot) { parts.push('<p class="notice">snapshot: ' + txt(d.snapshot) + "</p>"); }
    if (d.sha) { parts.push('<p class="notice">profile sha256: ' + txt(d.sha) + "</p>"); }
    return parts.join("");
  }

  function fill(sec) {
    if (sec.dataset.filled) { return; }
    sec.dataset.filled = "1";
    sec.insertAdjacentHTML("beforeend", body(DATA.devices[+sec.dataset.i]));
  }

  function runPage() {
    var devs = DATA.devices;
    devs.forEach(function (d, i) { d.i = i; });
    var order = devs.slice().sort(function (a, b) {   // failures first, then as run
      return (RANK[a.status] == null ? 9 : RANK[a.status]) - (RANK[b.status] == null ? 9 : RANK[b.status]) ||
             a.i - b.i;
    });
    var tbody = $("device-rows"), asFound = DATA.kind === "as-found";
    tbody.innerHTML = order.map(function (d) {
      var run = asFound ? "" : '<td class="num">' + esc(d.batch == null ? "" : d.batch) + '</td><td class="num">' +
             d.changed + '</td><td class="num">' + d.failed + '</td><td class="num">' + d.requests +
             '</td><td class="num">' + esc(d.seconds == null ? "" : d.seconds.toFixed(2)) + "</td>";
      return '<tr class="dev" data-i="' + d.i + '"><td>' + txt(d.name) + "</td><td>" + st(d.status) + "</td>" +
             run + "<td>" + txt(d.profile) + "</td></tr>";
    }).join("");
    // a compact record: parameters only for the devices that changed or did not end ok
    var listed = DATA.compact ? order.filter(function (d) { return d.changed > 0 || d.status !== "ok"; }) : order;
    var sections = $("records");
    sections.innerHTML = listed.map(function (d) {
      // devices that need a look are open; a run of a few devices shows them all
      var open = (RANK[d.status] != null && RANK[d.status] < 6) || devs.length <= 3 ? " open" : "";
      return '<details class="device" id="dev-' + d.i + '" data-i="' + d.i + '"' + open + "><summary>" +
             "<b>" + txt(d.name) + "</b> " + st(d.status) + '<span class="where">' + txt(d.url) + " unit " +
             esc(d.unit) + " &middot; " + txt(d.profile) + (d.batch == null ? "" : " &middot; batch " +
             esc(d.batch)) + "</span></summary></details>";
    }).join("");
    Array.prototype.forEach.call(sections.children, function (sec) {
      if (sec.open) { fill(sec); }
      sec.addEventListener("toggle", function () { if (sec.open) { fill(sec); } });
    });
    tbody.addEventListener("click", function (e) {
      var tr = e.target.closest("tr.dev");
      if (!tr) { return; }
      var sec = $("dev-" + tr.dataset.i);
      if (sec) { sec.open = true; fill(sec); sec.scrollIntoView(); }
    });
    sortable($("device-table"), tbody, function (tr, key) {
      var d = devs[+tr.dataset.i];
      return key === "status" ? (RANK[d.status] == null ? 9 : RANK[d.status]) : d[key];
    });
    filters(function (d) { return [d.name, d.url, d.profile].join(" "); });
  }

  function sortable(table, tbody, value) {
    table.querySelectorAll("th.sort").forEach(function (th) {
      th.addEventListener("click", function () {
        var key = th.dataset.key, dir = th.dataset.dir === "asc" ? "desc" : "asc";
        table.querySelectorAll("th.sort").forEach(function (o) { o.removeAttribute("data-dir"); });
        th.dataset.dir = dir;
        var rows = Array.prototype.slice.call(tbody.children);
        rows.sort(function (a, b) {
          var x = value(a, key), y = value(b, key);
          if (x == null) { x = ""; } if (y == null) { y = ""; }
          var c = (typeof x === "number" && typeof y === "number") ? x - y : String(x).localeCompare(String(y));
          return dir === "asc" ? c : -c;
        });
        rows.forEach(function (r) { tbody.appendChild(r); });
      });
    });
  }

  function filters(text) {
    var q = $("q"), status = $("status"), batch = $("batch"), changed = $("changed"), bad = $("bad");
    function apply() {
      var words = q.value.toLowerCase(), shown = 0;
      DATA.devices.forEach(function (d) {
        var keep = (!words || text(d).toLowerCase().indexOf(words) >= 0) &&
                   (!status.value || d.status === status.value) &&
                   (!batch || !batch.value || String(d.batch) === batch.value) &&
                   (!changed || !changed.checked || d.changed > 0) &&
                   (!bad.checked || d.status !== "ok");
        if (keep) { shown++; }
        var row = document.querySelector('tr.dev[data-i="' + d.i + '"]');
        if (row) { row.classList.toggle("hidden", !keep); }
        var sec = $("dev-" + d.i);
        if (sec) { sec.classList.toggle("hidden", !keep); }
      });
      $("shown").textContent = shown + " of " + DATA.devices.length + " devices shown";
      document.querySelectorAll(".count").forEach(function (b) {
        b.classList.toggle("active", b.dataset.status === status.value);
      });
    }
    // the filters live in the address too (#status=failed&q=press&batch=2&bad=1): a link shows the same view
    var hash = new URLSearchParams(location.hash.slice(1));
    q.value = hash.get("q") || ""; status.value = hash.get("status") || "";
    if (batch) { batch.value = hash.get("batch") || ""; }
    if (changed) { changed.checked = hash.get("changed") === "1"; }
    bad.checked = hash.get("bad") === "1";
    function remember() {
      var h = new URLSearchParams();
      if (q.value) { h.set("q", q.value); } if (status.value) { h.set("status", status.value); }
      if (batch && batch.value) { h.set("batch", batch.value); }
      if (changed && changed.checked) { h.set("changed", "1"); } if (bad.checked) { h.set("bad", "1"); }
      history.replaceState(null, "", h.toString() ? "#" + h.toString() : location.pathname);
    }
    [q, status, batch, changed, bad].forEach(function (el) {
      if (el) {
        el.addEventListener("input", function () { apply(); remember(); });
        el.addEventListener("change", function () { apply(); remember(); });
      }
    });
    document.querySelectorAll(".count").forEach(function (b) {
      b.addEventListener("click", function () {
        status.value = status.value === b.dataset.status ? "" : b.dataset.status; apply();
      });
    });
    apply();
  }

  // ---- the drift matrix ------------------------------------------------------------------------
  function driftPage() {
    var devs = DATA.devices, params = DATA.parameters, cells = DATA.cells;
    var head = "<tr><th>parameter</th>" + devs.map(function (d, j) {
      return '<th data-j="' + j + '">' + txt(d) + "</th>"; }).join("") + "</tr>";
    var rows = params.map(function (p, i) {
      var drifted = 0;
      var tds = cells[i].map(function (c, j) {
        if (c == null) { return '<td class="missing" data-j="' + j + '">-</td>'; }
        if (c.length > 1) {
          drifted++;
          return '<td class="drift" data-j="' + j + '" title="desired ' + esc(c[1]) + '">' + txt(c[0]) +
                 " &rarr; " + txt(c[1]) + "</td>";
        }
        return '<td class="same" data-j="' + j + '">' + txt(c[0]) + "</td>";
      }).join("");
      return '<tr data-i="' + i + '" data-drifted="' + drifted + '"><td>' + txt(p) + "</td>" + tds + "</tr>";
    }).join("");
    $("matrix").innerHTML = "<thead>" + head + "</thead><tbody>" + rows + "</tbody>";
    var q = $("q"), only = $("only-drift"), dq = $("dq");
    function apply() {
      var words = q.value.toLowerCase(), dw = dq.value.toLowerCase(), shown = 0;
      var keepDev = devs.map(function (d, j) {
        var any = cells.some(function (row) { return row[j] && row[j].length > 1; });
        return (!dw || d.toLowerCase().indexOf(dw) >= 0) && (!only.checked || any);
      });
      document.querySelectorAll("#matrix [data-j]").forEach(function (el) {
        el.classList.toggle("hidden", !keepDev[+el.dataset.j]);
      });
      document.querySelectorAll("#matrix tbody tr").forEach(function (tr) {
        var keep = (!words || params[+tr.dataset.i].toLowerCase().indexOf(words) >= 0) &&
                   (!only.checked || +tr.dataset.drifted > 0);
        tr.classList.toggle("hidden", !keep);
        if (keep) { shown++; }
      });
      $("shown").textContent = shown + " of " + params.length + " parameters shown";
    }
    [q, only, dq].forEach(function (el) { el.addEventListener("input", apply); el.addEventListener("change", apply); });
    apply();
  }

  // the audit trail's page is drawn whole by deployer (audit show chose its records): nothing to draw here
  if (DATA.kind === "drift") { driftPage(); } else if (DATA.kind !== "audit") { runPage(); }
  // printing is the commissioning record: every device's section, open, with its table
  window.addEventListener("beforeprint", function () {
    document.querySelectorAll("details.device").forEach(function (sec) { fill(sec); sec.open = true; });
  });
  // drawn: how long the page's script took, for the benchmarks (performance.now() counts from navigation)
  document.documentElement.dataset.ready = String(Math.round(performance.now()));
})();
"""
