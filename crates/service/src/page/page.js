// compgate live status: polls /api/status once per status interval and redraws.
// Plain JavaScript, no library and no build step: the gateway embeds this file.
"use strict";

const $ = (id) => document.getElementById(id);

function esc(s) {
  return String(s ?? "").replace(/[&<>"']/g, (c) => ({
    "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;",
  })[c]);
}

function fmt(v, digits, unit) {
  if (v === null || v === undefined) return "-";
  return v.toFixed(digits) + (unit ? " " + unit : "");
}

function fmtExp(v) {
  if (v === null || v === undefined) return "-";
  return v.toExponential(3);
}

function badge(cls, text) {
  return `<span class="badge ${esc(cls)}">${esc(text)}</span>`;
}

// An inline SVG sparkline of [[t_unix_ms, value_degc|null, quality], ...]: the line
// of the values, bad stretches shaded, min and max at the right.
function sparkline(trend) {
  const w = 180, h = 34, right = 34;
  const pts = trend.filter((p) => p[1] !== null);
  if (trend.length < 2 || pts.length < 1) {
    return `<svg class="spark" width="${w}" height="${h}"></svg>`;
  }
  const t0 = trend[0][0], t1 = trend[trend.length - 1][0];
  const span = Math.max(t1 - t0, 1);
  let lo = Math.min(...pts.map((p) => p[1])), hi = Math.max(...pts.map((p) => p[1]));
  if (hi - lo < 0.1) { const m = (hi + lo) / 2; lo = m - 0.05; hi = m + 0.05; }
  const x = (t) => ((t - t0) / span) * (w - right - 2) + 1;
  const y = (v) => h - 3 - ((v - lo) / (hi - lo)) * (h - 6);
  let shade = "";
  trend.forEach((p, i) => {
    if (p[2] === 2 && i + 1 < trend.length) {
      shade += `<rect class="badseg" x="${x(p[0]).toFixed(1)}" y="0" width="${Math.max(x(trend[i + 1][0]) - x(p[0]), 1).toFixed(1)}" height="${h}"/>`;
    }
  });
  const line = pts.map((p) => `${x(p[0]).toFixed(1)},${y(p[1]).toFixed(1)}`).join(" ");
  return `<svg class="spark" width="${w}" height="${h}" viewBox="0 0 ${w} ${h}">${shade}` +
    `<polyline points="${line}"/>` +
    `<text x="${w - right + 3}" y="10">${hi.toFixed(1)}</text>` +
    `<text x="${w - right + 3}" y="${h - 2}">${lo.toFixed(1)}</text></svg>`;
}

// A bad channel's value is only the last good one held: shown as none, as the status
// line and `compgate probe` show it (the trend keeps it, shaded bad).
function channels(list) {
  $("channels").tBodies[0].innerHTML = list.map((c) => `
    <tr class="${esc(c.quality)}" data-channel="${esc(c.name)}" data-quality="${esc(c.quality)}">
      <td>${esc(c.name)}</td>
      <td class="num value">${c.quality === "bad" ? "-" : fmt(c.value_degc, 2, "°C")}</td>
      <td>${badge(c.quality, c.quality_text)}</td>
      <td class="num">${fmt(c.current_ma, 2)}</td>
      <td>${sparkline(c.trend)}</td>
    </tr>`).join("");
}

function devices(list) {
  $("devices").tBodies[0].innerHTML = list.map((d) => `
    <tr data-device="${esc(d.name)}" data-state="${esc(d.state)}">
      <td>${esc(d.name)}</td>
      <td class="muted">${esc(d.link)}</td>
      <td>${badge(d.state, d.state)}</td>
      <td class="num">${d.cycles}</td>
      <td class="num">${d.failed_cycles}</td>
      <td class="num">${d.connects}</td>
      <td class="num">${fmt(d.last_cycle_ms, 1, "ms")}</td>
    </tr>${d.last_error ? `<tr class="error-row"><td></td><td colspan="6" class="wrap">${esc(d.last_error)}</td></tr>` : ""}`).join("");
}

function paramRow(label, p) {
  if (!p) return `<tr><td>${label}</td><td class="num">-</td><td class="num">-</td><td class="num">-</td></tr>`;
  return `<tr><td>${label}</td><td class="num">${fmt(p.sd43900_mm, 4, "mm")}</td>` +
    `<td class="num">${fmtExp(p.sd43910)}</td><td class="num">${fmt(p.sd43920_mm, 1, "mm")}</td></tr>`;
}

function axes(list) {
  $("axes").innerHTML = list.map((a) => {
    const nc = a.nc;
    const mode = a.shadow ? badge("shadow", "shadow: NC not written") : "";
    const ncLine = nc
      ? `NC applies <b>${fmt(nc.applied_comp_mm, 4, "mm")}</b> at ${fmt(nc.position_mm, 1, "mm")}` +
        ` (moving to ${fmt(nc.target_comp_mm, 4, "mm")}); MD32750 ${nc.md32750}; ` +
        (nc.referenced ? "referenced" : "<b>not referenced</b>")
      : "NC not read yet";
    return `<div class="axis" data-axis="${esc(a.name)}" data-shadow="${a.shadow}">
      <h3>Axis ${esc(a.name)} ${mode}</h3>
      <table>
        <thead><tr><th></th><th class="num">SD43900 K0</th><th class="num">SD43910 tan β</th><th class="num">SD43920 P0</th></tr></thead>
        <tbody>
          ${paramRow("last written", a.written)}
          ${a.shadow ? paramRow("would write", a.would_write) : ""}
          ${paramRow("NC holds", nc)}
        </tbody>
      </table>
      <p>${ncLine}</p>
      <p class="${a.at_limit ? "warning" : "muted"}">decision: ${esc(a.decision)}; jobs ${a.jobs_ok} ok, ${a.jobs_failed} failed</p>
      ${a.warning ? `<p class="warning">${esc(a.warning)}</p>` : ""}
      ${a.last_job_error ? `<p class="warning">last job: ${esc(a.last_job_error)}</p>` : ""}
    </div>`;
  }).join("") || `<p class="muted">No axis configured (monitoring only).</p>`;
}

function jobs(list) {
  $("no-jobs").hidden = list.length > 0;
  // The newest dozen fit the screen; /api/status has all it keeps.
  $("jobs").tBodies[0].innerHTML = list.slice(0, 12).map((j) => {
    const result = j.shadow ? "shadow" : (j.ok ? "ok" : "failed");
    return `<tr data-result="${result}">
      <td>${clock(j.t_unix_ms)}</td>
      <td>${esc(j.axis)}</td>
      <td>${badge(result, result)}</td>
      <td class="num">${fmt(j.params.sd43900_mm, 4, "mm")}</td>
      <td class="num">${fmtExp(j.params.sd43910)}</td>
      <td class="num">${fmt(j.params.sd43920_mm, 1, "mm")}</td>
      <td class="num">${j.job_id ?? "-"}</td>
      <td class="num">${fmt(j.elapsed_ms, 1, "ms")}</td>
      <td class="wrap">${esc(j.error ?? "")}</td>
    </tr>`;
  }).join("");
}

// HH:MM:SS, the same on every machine.
function clock(t_unix_ms) {
  const d = new Date(t_unix_ms);
  return [d.getHours(), d.getMinutes(), d.getSeconds()].map((n) => String(n).padStart(2, "0")).join(":");
}

function live(state, text) {
  $("live").dataset.state = state;
  $("live-text").textContent = text;
}

let intervalMs = 1000;

async function refresh() {
  try {
    const r = await fetch("api/status", { cache: "no-store" });
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const s = await r.json();
    intervalMs = Math.min(Math.max(s.interval_s * 1000, 250), 5000);
    $("shadow-banner").hidden = !s.shadow;
    channels(s.channels);
    axes(s.axes);
    devices(s.devices);
    jobs(s.jobs);
    document.body.dataset.samples = s.samples;
    live("live", `live ${clock(s.t_unix_ms)}, ${s.samples} samples`);
    $("trend-span").textContent = `trend, last ${Math.round(s.trend_s / 60 * 10) / 10} min`;
  } catch (e) {
    // The gateway restarting or gone: say so on the page, keep trying.
    live("stale", `no answer from the gateway (${e.message}); retrying`);
  }
  setTimeout(refresh, intervalMs);
}

refresh();
