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

// tan β: "0" for none, else 3 digits in exponent form ("1.150e-4").
function fmtExp(v) {
  if (v === null || v === undefined) return "-";
  if (v === 0) return "0";
  return v.toExponential(3);
}

function badge(cls, text) {
  return `<span class="badge ${esc(cls)}">${esc(text)}</span>`;
}

// A time in the browser's zone, named ("14:03:07 CET"), with the date in front
// when it is not today's: an operator reads it against the clock on the wall.
function clock(t_unix_ms) {
  const d = new Date(t_unix_ms);
  const time = d.toLocaleTimeString("en-GB", {
    hour: "2-digit", minute: "2-digit", second: "2-digit", hourCycle: "h23", timeZoneName: "short",
  });
  const now = new Date();
  if (d.getFullYear() === now.getFullYear() && d.getMonth() === now.getMonth() &&
      d.getDate() === now.getDate()) {
    return time;
  }
  const day = [d.getFullYear(), d.getMonth() + 1, d.getDate()]
    .map((n) => String(n).padStart(2, "0")).join("-");
  return `${day} ${time}`;
}

// "12 s" / "4 min" / "3 h": how long ago, for an age in ms.
function ago(ms) {
  const s = Math.max(ms, 0) / 1000;
  if (s < 90) return `${Math.round(s)} s`;
  if (s < 5400) return `${Math.round(s / 60)} min`;
  return `${Math.round(s / 3600)} h`;
}

// Below this span the trend is drawn flat around its mean: ±0.05 °C of noise is
// not a swing of the machine.
const MIN_SPAN_DEGC = 1.0;

// An inline SVG sparkline of [[t_unix_ms, value_degc|null, quality], ...] over the
// trend window ending at `now_ms` (the gateway's clock, as the points'): the newest
// value at the right, no data yet at the left; bad stretches shaded, max and min at
// the right.
function sparkline(trend, now_ms, window_ms) {
  const w = 190, h = 34, right = 44;
  const pts = trend.filter((p) => p[1] !== null);
  if (trend.length < 2 || pts.length < 1) {
    return `<svg class="spark" width="${w}" height="${h}"></svg>`;
  }
  const t0 = now_ms - window_ms;
  let lo = Math.min(...pts.map((p) => p[1])), hi = Math.max(...pts.map((p) => p[1]));
  if (hi - lo < MIN_SPAN_DEGC) {
    const m = (hi + lo) / 2;
    lo = m - MIN_SPAN_DEGC / 2;
    hi = m + MIN_SPAN_DEGC / 2;
  }
  const x = (t) => Math.max((t - t0) / window_ms, 0) * (w - right - 2) + 1;
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
    `<text x="${w - right + 3}" y="10">${hi.toFixed(1)} °C</text>` +
    `<text x="${w - right + 3}" y="${h - 2}">${lo.toFixed(1)} °C</text></svg>`;
}

const RANK = { bad: 0, uncertain: 1, good: 2 };

// Bad channels first, then uncertain, then good; config order within each (sort is
// stable). A bad channel's value is only the last good one held: shown as none, as
// the status line and `compgate probe` show it (the trend keeps it, shaded bad).
function channels(list, now_ms, window_ms) {
  const sorted = list.slice().sort((a, b) => (RANK[a.quality] ?? 1) - (RANK[b.quality] ?? 1));
  $("channels").tBodies[0].innerHTML = sorted.map((c) => `
    <tr class="${esc(c.quality)}" data-channel="${esc(c.name)}" data-quality="${esc(c.quality)}">
      <td class="name" title="${esc(c.name)}">${esc(c.name)}</td>
      <td class="num value">${c.quality === "bad" ? "-" : fmt(c.value_degc, 2, "°C")}</td>
      <td>${badge(c.quality, c.quality_text)}</td>
      <td class="num">${fmt(c.current_ma, 2)}</td>
      <td>${sparkline(trends.get(c.name) ?? [], now_ms, window_ms)}</td>
    </tr>`).join("");
}

// "poll took": the last poll cycle's duration; "answered": how long ago a cycle last
// got an answer (the gateway's ages, so the browser's clock does not matter).
function devices(list) {
  $("devices").tBodies[0].innerHTML = list.map((d) => `
    <tr data-device="${esc(d.name)}" data-state="${esc(d.state)}">
      <td>${esc(d.name)}</td>
      <td class="muted link" title="${esc(d.link)}">${esc(d.link)}</td>
      <td>${badge(d.state, d.state)}</td>
      <td class="num">${d.answered_ago_ms === null || d.answered_ago_ms === undefined ? "never" : ago(d.answered_ago_ms) + " ago"}</td>
      <td class="num">${d.cycles}</td>
      <td class="num">${d.failed_cycles}</td>
      <td class="num">${d.connects}</td>
      <td class="num">${fmt(d.last_cycle_ms, 1, "ms")}</td>
    </tr>${d.last_error ? `<tr class="error-row"><td></td><td colspan="7" class="wrap">${esc(d.last_error)}</td></tr>` : ""}`).join("");
}

function paramRow(label, p) {
  if (!p) return `<tr><td>${label}</td><td class="num">-</td><td class="num">-</td><td class="num">-</td></tr>`;
  return `<tr><td>${label}</td><td class="num">${fmt(p.sd43900_mm, 4, "mm")}</td>` +
    `<td class="num">${fmtExp(p.sd43910)}</td><td class="num">${fmt(p.sd43920_mm, 1, "mm")}</td></tr>`;
}

function held(a) {
  return a.decision.startsWith("hold");
}

// The axis' state in words for the summary, as its badges say it.
function axisWords(a) {
  const w = [];
  if (a.shadow) w.push("shadow");
  if (held(a)) w.push("held");
  if (a.at_limit) w.push("at its limit");
  if (a.outside_fit) w.push("outside its fit");
  return w.length ? w.join(", ") : "ok";
}

function ncLine(nc) {
  // A target reached for its setting data only (OPC UA, ADS) reports no axis state;
  // the S7 block's FB3 program leaves the applied compensation out.
  if (nc.position_mm === null) {
    return "its NC target reports the setting data only: no position, applied compensation or referenced flag";
  }
  const applied = nc.applied_comp_mm === null
    ? "NC reports no applied compensation,"
    : `NC applies <b>${fmt(nc.applied_comp_mm, 4, "mm")}</b> (moving to ${fmt(nc.target_comp_mm, 4, "mm")})`;
  return `${applied} at ${fmt(nc.position_mm, 1, "mm")}; MD32750 ${nc.md32750}; ` +
    (nc.referenced ? "referenced" : "<b>not referenced</b>");
}

function axes(list, now_ms) {
  $("axes").innerHTML = list.map((a) => {
    // Not answering now: the values it held when last read, with that time.
    const nc = a.nc ?? a.nc_last;
    const asRead = !a.nc && a.nc_last ? ` (as read ${clock(now_ms - a.nc_last.read_ago_ms)})` : "";
    const line = a.nc
      ? ncLine(a.nc)
      : (a.nc_last ? `<b>NC not answering</b>; as read ${clock(now_ms - a.nc_last.read_ago_ms)}: ${ncLine(a.nc_last)}` : "NC not read yet");
    const badges = (held(a) ? badge("hold", "HOLD") : "") +
      (a.at_limit ? badge("limit", "AT LIMIT") : "") +
      (a.outside_fit ? badge("limit", "OUTSIDE FIT") : "") +
      (a.shadow ? badge("shadow", "SHADOW: NC not written") : "");
    const jobsText = a.shadow
      ? `jobs ${a.jobs_shadow ?? 0} shadow`
      : `jobs ${a.jobs_ok} ok, ${a.jobs_failed} failed`;
    return `<div class="axis" data-axis="${esc(a.name)}" data-shadow="${a.shadow}" data-held="${held(a)}" data-at-limit="${a.at_limit}">
      <h3>Axis ${esc(a.name)} ${badges}</h3>
      <table>
        <thead><tr><th></th><th class="num">SD43900 K0</th><th class="num">SD43910 tan β</th><th class="num">SD43920 P0</th></tr></thead>
        <tbody>
          ${paramRow("last written", a.written)}
          ${a.shadow ? paramRow("would write", a.would_write) : ""}
          ${paramRow("NC holds" + asRead, nc)}
        </tbody>
      </table>
      <p>${line}</p>
      <p class="${a.at_limit || held(a) ? "warning" : "muted"}">decision: ${esc(a.decision)}; ${jobsText}</p>
      ${a.warning ? `<p class="warning">${esc(a.warning)}</p>` : ""}
      ${a.outside_fit ? `<p class="warning">model: ${esc(a.outside_fit)}</p>` : ""}
      ${a.last_job_error ? `<p class="warning">last job: ${esc(a.last_job_error)}</p>`
        : a.last_failure ? `<p class="muted">last failed job ${clock(a.last_failure.t_unix_ms)}: ${esc(a.last_failure.error)}</p>` : ""}
    </div>`;
  }).join("") || `<p class="muted">No axis configured (monitoring only).</p>`;
}

// The page-wide banner names the axes in shadow mode; "the NC is not written" only
// when no axis writes it.
function shadowBanner(list) {
  const names = list.filter((a) => a.shadow).map((a) => a.name);
  $("shadow-banner").hidden = names.length === 0;
  if (names.length === 0) return;
  const all = names.length === list.length;
  $("shadow-banner").textContent =
    `SHADOW MODE on axis ${names.join(", ")}: the gateway computes and records what it would write` +
    (all ? "; the NC is not written." : ` and does not write ${names.length > 1 ? "them" : "it"}; the other axes are written.`);
}

// One line at the top: what needs a look, before hundreds of channel rows.
function summary(s) {
  const n = { bad: 0, uncertain: 0 };
  s.channels.forEach((c) => { if (c.quality in n) n[c.quality] += 1; });
  const parts = [];
  const ch = [];
  if (n.bad) ch.push(`<span class="s-bad">${n.bad} bad</span>`);
  if (n.uncertain) ch.push(`<span class="s-warn">${n.uncertain} uncertain</span>`);
  parts.push(`${s.channels.length} channels: ${ch.length ? ch.join(", ") : "all good"}`);
  const up = s.devices.filter((d) => d.state === "up").length;
  parts.push(`devices: <span class="${up < s.devices.length ? "s-bad" : ""}">${up} of ${s.devices.length} up</span>`);
  if (s.axes.length) {
    parts.push("axis " + s.axes.map((a) => {
      const w = axisWords(a);
      return `<span class="${w === "ok" ? "" : "s-warn"}">${esc(a.name)} ${w}</span>`;
    }).join(", "));
  }
  const el = $("summary");
  el.innerHTML = parts.join(" · ");
  el.dataset.bad = n.bad;
  el.dataset.uncertain = n.uncertain;
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
      <td class="error">${esc(j.error ?? "")}</td>
    </tr>`;
  }).join("");
}

function live(state, text) {
  $("live").dataset.state = state;
  $("live-text").textContent = text;
}

// The trends come with every TREND_EVERY_MS-th answer only (at 384 channels they are
// 3.6 MB of the 3.7 MB); in between each trend is extended by the value just read.
const TREND_EVERY_MS = 10000;
const trends = new Map();
let trendsAtMs = -Infinity;

function keepTrends(s) {
  const window_ms = s.trend_s * 1000;
  for (const c of s.channels) {
    if (c.trend) {
      trends.set(c.name, c.trend);
    } else if (trends.has(c.name)) {
      const t = trends.get(c.name);
      const q = RANK[c.quality] === undefined ? 1 : 2 - RANK[c.quality];
      t.push([s.t_unix_ms, c.value_degc, q]);
      while (t.length && s.t_unix_ms - t[0][0] > window_ms) t.shift();
    }
  }
}

let intervalMs = 1000;
// Ages are measured on the browser's monotonic clock, never against the gateway's
// t_unix_ms: the two clocks may differ.
let lastAnswerPerf = null;
let lastAnswerWall = null;
let lastDataMs = null;
let lastError = "";

// Stale after about 3 status intervals without an answer, 3 s at least (a large
// answer over a tablet's Wi-Fi takes a while).
function staleAfterMs() {
  return Math.max(3 * intervalMs, 3000);
}

function checkStale() {
  const since = lastAnswerPerf === null ? null : performance.now() - lastAnswerPerf;
  if (since === null || since <= staleAfterMs()) return;
  document.body.classList.add("stale");
  $("stale-banner").hidden = false;
  $("stale-banner").textContent = `Data of ${clock(lastDataMs)}, not live: no answer from the gateway for ${ago(since)}.`;
  live("stale", `no answer since ${clock(lastAnswerWall)}${lastError ? ` (${lastError})` : ""}; retrying`);
}

async function refresh() {
  const abort = new AbortController();
  const timer = setTimeout(() => abort.abort(), staleAfterMs());
  try {
    const now = performance.now();
    const full = now - trendsAtMs >= TREND_EVERY_MS;
    const r = await fetch(full ? "api/status" : "api/status?trend=0",
      { cache: "no-store", signal: abort.signal });
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const s = await r.json();
    if (full) trendsAtMs = now;
    // The channel set changed (a reload): the trends of the new names next time.
    if (s.channels.some((c) => !c.trend && !trends.has(c.name))) trendsAtMs = -Infinity;
    intervalMs = Math.min(Math.max(s.interval_s * 1000, 250), 5000);
    keepTrends(s);
    shadowBanner(s.axes);
    summary(s);
    channels(s.channels, s.t_unix_ms, s.trend_s * 1000);
    axes(s.axes, s.t_unix_ms);
    devices(s.devices);
    jobs(s.jobs);
    document.body.dataset.samples = s.samples;
    lastAnswerPerf = performance.now();
    lastAnswerWall = Date.now();
    lastDataMs = s.t_unix_ms;
    lastError = "";
    document.body.classList.remove("stale");
    $("stale-banner").hidden = true;
    live("live", `live, data of ${clock(s.t_unix_ms)}`);
    $("trend-span").textContent = `trend, last ${Math.round(s.trend_s / 60 * 10) / 10} min`;
  } catch (e) {
    // The gateway restarting, gone or hung: say so on the page, keep trying.
    lastError = e.name === "AbortError" ? `none within ${ago(staleAfterMs())}` : e.message;
    if (lastAnswerPerf === null) live("stale", `no answer from the gateway (${lastError}); retrying`);
    checkStale();
  } finally {
    clearTimeout(timer);
  }
  setTimeout(refresh, intervalMs);
}

// A fetch that hangs must not keep the page looking live until it times out.
setInterval(checkStale, 500);
refresh();
