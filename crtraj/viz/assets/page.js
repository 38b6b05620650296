// crtraj's page around meshcat's scene: heads-up panel, plots, events, controls, legend.
// Reads and drives meshcat's animation clock (viewer.animator); every number comes from the
// JSON in #crtraj-data (mm, s). window.crtrajView is the page's small API (tests, PNG/MP4 export).
(function () {
  "use strict";
  let data = JSON.parse(document.getElementById("crtraj-data").textContent);
  let runs = data.runs;
  const STATUS_COLORS = { move: "#2e7d32", suboptimal: "#8d8a12", fallback: "#e65100", hold: "#6a1b9a",
    unsafe: "#c62828", stale: "#455a64", estop: "#000000" };
  const EVENT_COLORS = { replan: "#1565c0", fallback: "#e65100", hold: "#6a1b9a", deadline: "#c62828",
    estop: "#000000", dropout: "#455a64", unsafe: "#c62828" };
  const OBSTACLE_LINES = ["#d62728", "#ff7f0e", "#8c564b", "#e377c2", "#7f7f7f"];
  const $ = (id) => document.getElementById(id);
  const lastT = () => Math.max(0, ...runs.map((r) => (r.t.length ? r.t[r.t.length - 1] : 0)));
  let duration = lastT();
  let frames = runs.length && runs[0].t.length ? runs[0].t : [0];
  let shownTime = 0; // the page's time when meshcat has no animation to keep it
  let ready = false;

  const animator = () => (window.viewer && window.viewer.animator) || null;
  const hasClock = () => { const a = animator(); return !!(a && a.actions && a.actions.length); };
  const now = () => (hasClock() ? animator().time : shownTime);
  const playing = () => hasClock() && animator().playing;
  const fmt = (v, d, unit) => (v === null || v === undefined ? "\u2014" : v.toFixed(d) + (unit ? " " + unit : ""));
  const fmtPct = (v) => (v === null || v === undefined ? "\u2014" : (100 * v).toFixed(0) + " %");

  function indexAt(t, ts) { // the last waypoint at or before t (the step that is on screen)
    let lo = 0, hi = ts.length - 1;
    if (hi < 0) return -1;
    while (lo < hi) { const mid = (lo + hi + 1) >> 1; if (ts[mid] <= t + 1e-6) lo = mid; else hi = mid - 1; }
    return lo;
  }

  // ------------------------------------------------------------ the clock
  function seek(t) {
    t = Math.max(0, Math.min(duration, t));
    shownTime = t;
    if (hasClock()) {
      const a = animator();
      for (const act of a.actions) act.play(); // an action meshcat never played is inactive: seeking would not move it
      a.seek(t);
      a.display_progress(t);
    }
    refresh();
  }
  function play() {
    if (!hasClock()) return;
    const a = animator();
    if (now() >= duration - 1e-6) seek(0);
    const t = now();
    for (const act of a.actions) { act.paused = false; act.time = Math.min(act._clip.duration, t); }
    a.play();
  }
  function pause() { if (hasClock()) { const t = now(); animator().pause(); seek(t); } }
  function toggle() { if (playing()) pause(); else play(); }
  function step(dir) {
    pause();
    const i = indexAt(now(), frames);
    seek(frames[Math.max(0, Math.min(frames.length - 1, i + dir))]);
  }
  function setSpeed(s) { if (hasClock()) animator().mixer.timeScale = s; $("crtraj-speed").value = String(s); }

  // ------------------------------------------------------------ the panel
  function statusBadge(s) {
    if (!s) return "\u2014";
    return `<span class="crtraj-status" style="background:${STATUS_COLORS[s] || "#555"}">${s}</span>`;
  }
  function row(key, name, value, bad) {
    return `<tr><td>${name}</td><td class="v${bad ? " crtraj-bad" : ""}" data-key="${key}">${value}</td></tr>`;
  }
  function hudRun(r, ri, t) {
    const k = indexAt(t, r.t);
    const prefix = runs.length > 1 ? r.label + " " : "";
    let h = `<h2>${runs.length > 1 ? "run " + r.label + (ri ? " (ghost)" : "") : r.kind === "plan" ? "plan" : "run"}</h2><table>`;
    h += row(`${ri}-status`, prefix + "step", statusBadge(r.status[k]));
    r.obstacles.forEach((name, i) => {
      const c = r.clearance[i][k];
      const dist = c === null ? null : c + r.safety_distance;
      h += row(`${ri}-distance-${i}`, `to ${name}`, fmt(dist, 2, "mm"), dist !== null && dist < 0);
      h += row(`${ri}-clearance-${i}`, `&nbsp;&nbsp;beyond D_sf`, fmt(c, 2, "mm"), c !== null && c < 0);
    });
    h += row(`${ri}-tip_error`, "tip error", fmt(r.tip_error[k], 2, "mm"));
    const it = r.iteration[k];
    const late = it !== null && r.deadline !== null && it > r.deadline;
    const dl = r.deadline === null ? "" : ` / ${(1e3 * r.deadline).toFixed(1)}`;
    h += row(`${ri}-iteration`, "iteration", it === null ? "\u2014" : (1e3 * it).toFixed(2) + dl + " ms", late);
    h += row(`${ri}-velocity`, "velocity of limit", fmtPct(r.velocity[k]), r.velocity[k] > 1);
    h += row(`${ri}-acceleration`, "accel. of limit", fmtPct(r.acceleration[k]), r.acceleration[k] > 1);
    return h + `</table>`;
  }
  function refresh() {
    const t = now();
    $("crtraj-time").textContent = `t = ${t.toFixed(2)} s`;
    $("crtraj-time").dataset.t = String(t);
    $("crtraj-hud").innerHTML = `<div class="crtraj-clock">D_sf ${runs.length ? runs[0].safety_distance : 0} mm</div>` +
      runs.map((r, i) => hudRun(r, i, t)).join("");
    $("crtraj-play").innerHTML = playing() ? "&#10074;&#10074;" : "&#9654;";
    for (const p of plots) p.cursor(t);
  }

  // ------------------------------------------------------------ the plots
  function Plot(title, unit, series, refLine, cap, refName) { // cap: top of the y axis (larger values drawn at the top)
    const box = document.createElement("div");
    box.className = "crtraj-plot";
    const cv = document.createElement("canvas");
    box.appendChild(cv);
    $("crtraj-plots").appendChild(box);
    let lo = 0, hi = 1, base = null;
    for (const s of series) for (const v of s.y) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    if (refLine !== null) hi = Math.max(hi, refLine * 1.5);
    if (cap) hi = Math.min(hi, cap);
    const pad = { l: 44, r: 8, t: 16, b: 16 };
    const X = (t, w) => pad.l + (w - pad.l - pad.r) * (duration > 0 ? t / duration : 0);
    const Y = (v, h) => h - pad.b - (h - pad.t - pad.b) * (Math.min(v, hi) - lo) / (hi - lo || 1);
    function draw() {
      const dpr = window.devicePixelRatio || 1;
      cv.width = Math.max(1, cv.clientWidth * dpr); cv.height = Math.max(1, cv.clientHeight * dpr);
      const g = cv.getContext("2d"); g.scale(dpr, dpr);
      const w = cv.clientWidth, h = cv.clientHeight;
      g.fillStyle = "#fff"; g.fillRect(0, 0, w, h);
      g.strokeStyle = "#d5d9df"; g.strokeRect(pad.l, pad.t, w - pad.l - pad.r, h - pad.t - pad.b);
      g.fillStyle = "#414852"; g.font = "11px system-ui, sans-serif";
      g.fillText(`${title} (${unit})`, pad.l, 11);
      g.fillText(hi.toPrecision(3), 2, pad.t + 8); g.fillText(lo.toPrecision(3), 2, h - pad.b);
      if (refLine !== null) {
        g.setLineDash([5, 4]); g.strokeStyle = "#c62828"; g.beginPath();
        g.moveTo(pad.l, Y(refLine, h)); g.lineTo(w - pad.r, Y(refLine, h)); g.stroke(); g.setLineDash([]);
        g.fillStyle = "#c62828"; g.fillText(refName, w - pad.r - 50, Y(refLine, h) - 3);
      }
      for (const s of series) {
        g.strokeStyle = s.color; g.lineWidth = 1.5; g.setLineDash(s.dash ? [4, 3] : []); g.beginPath();
        let pen = false;
        s.y.forEach((v, i) => {
          if (v === null) { pen = false; return; }
          if (pen) g.lineTo(X(s.t[i], w), Y(v, h)); else g.moveTo(X(s.t[i], w), Y(v, h));
          pen = true;
        });
        g.stroke();
      }
      g.setLineDash([]);
      base = g.getImageData(0, 0, cv.width, cv.height);
    }
    cv.addEventListener("click", (ev) => {
      const rect = cv.getBoundingClientRect();
      const f = (ev.clientX - rect.left - pad.l) / (rect.width - pad.l - pad.r);
      pause(); seek(f * duration);
    });
    return {
      draw,
      cursor(t) {
        if (!base) draw();
        const g = cv.getContext("2d");
        g.putImageData(base, 0, 0);
        const dpr = window.devicePixelRatio || 1;
        g.save(); g.setTransform(dpr, 0, 0, dpr, 0, 0);
        g.strokeStyle = "#111"; g.lineWidth = 1.5; g.beginPath();
        g.moveTo(X(t, cv.clientWidth), pad.t); g.lineTo(X(t, cv.clientWidth), cv.clientHeight - pad.b); g.stroke();
        g.restore();
      },
    };
  }
  const plots = [];
  function buildPlots() {
    if (!runs.length) return;
    const dist = [], tip = [], iter = [];
    runs.forEach((r, ri) => {
      r.obstacles.forEach((name, i) => dist.push({ t: r.t, dash: ri > 0, color: OBSTACLE_LINES[i % OBSTACLE_LINES.length],
        y: r.clearance[i].map((c) => (c === null ? null : c + r.safety_distance)) }));
      tip.push({ t: r.t, dash: ri > 0, color: "#1f77b4", y: r.tip_error });
      iter.push({ t: r.t, dash: ri > 0, color: "#555", y: r.iteration.map((v) => (v === null ? null : 1e3 * v)) });
    });
    if (dist.length) plots.push(Plot("distance to obstacles", "mm", dist, runs[0].safety_distance, Math.max(40, 8 * runs[0].safety_distance), "D_sf"));
    if (tip.some((s) => s.y.some((v) => v !== null))) plots.push(Plot("tip error", "mm", tip, null));
    const dl = runs[0].deadline;
    if (iter.some((s) => s.y.some((v) => v !== null))) plots.push(Plot("iteration time", "ms", iter, dl === null ? null : 1e3 * dl, dl === null ? 0 : 4e3 * dl, "deadline"));
    for (const p of plots) p.draw();
  }

  // ------------------------------------------------------------ events and legend
  function buildEvents() {
    const bar = $("crtraj-events");
    runs.forEach((r, ri) => r.events.forEach((e) => {
      const m = document.createElement("div");
      m.className = "crtraj-event";
      m.style.left = `calc(44px + (100% - 52px) * ${duration > 0 ? e.t / duration : 0})`;
      m.style.background = EVENT_COLORS[e.kind] || "#555";
      m.dataset.kind = e.kind; m.dataset.t = String(e.t);
      m.title = `${runs.length > 1 ? r.label + ": " : ""}${e.kind} at ${e.t.toFixed(2)} s: ${e.text}`;
      m.addEventListener("click", () => { pause(); seek(e.t); });
      bar.appendChild(m);
    }));
    const closest = $("crtraj-verdict");
    closest.textContent = runs.map((r) => (runs.length > 1 ? r.label + ": " : "") + r.verdict +
      (r.headline ? ` \u00b7 ${r.headline}` : "")).join("  |  ");
    closest.title = closest.textContent;
  }
  function setLayer(path, on) {
    if (!window.viewer) return;
    window.viewer.set_property(["meshcat", ...path.split("/")], "visible", on);
    window.viewer.set_dirty();
  }
  function buildLegend() {
    const box = $("crtraj-legend");
    for (const item of data.legend) {
      const label = document.createElement("label");
      const sw = `<span class="crtraj-swatch" style="background:${item.color}"></span>`;
      if (item.layer) {
        const on = item.on !== false;
        label.innerHTML = `<input type="checkbox"${on ? " checked" : ""}>${sw}${item.label}`;
        label.querySelector("input").addEventListener("change", (ev) => setLayer(item.layer, ev.target.checked));
      } else {
        label.innerHTML = `<span style="width:13px"></span>${sw}${item.label}`;
      }
      box.appendChild(label);
    }
    Object.entries(EVENT_COLORS).forEach(([k, c]) => {
      if (!runs.some((r) => r.events.some((e) => e.kind === k))) return;
      const label = document.createElement("label");
      label.innerHTML = `<span style="width:13px"></span><span class="crtraj-swatch" style="background:${c}"></span>event: ${k}`;
      box.appendChild(label);
    });
  }

  // ------------------------------------------------------------ wiring
  function fitPane() {
    const pane = document.getElementById("meshcat-pane");
    if (window.viewer && pane) window.viewer.set_3d_pane_size(pane.clientWidth, pane.clientHeight);
  }
  function project(p) { // a point (mm, world frame) to page pixels with the page's camera
    const v = window.viewer, root = v.scene_tree.find(["meshcat"]).object;
    root.updateMatrixWorld(true); v.camera.updateMatrixWorld(true);
    const q = root.position.clone().set(p[0] * 1e-3, p[1] * 1e-3, p[2] * 1e-3);
    root.localToWorld(q); q.project(v.camera);
    const r = v.renderer.domElement.getBoundingClientRect();
    return [r.left + (q.x + 1) / 2 * r.width, r.top + (1 - q.y) / 2 * r.height];
  }
  function start() {
    fitPane();
    const hash = new URLSearchParams(location.hash.slice(1));
    if (hash.has("t")) { if (hasClock()) animator().pause(); seek(parseFloat(hash.get("t")) || 0); }
    else if (!playing()) seek(data.live ? duration : 0); // meshcat activates its actions only when it plays: a paused page seeks
    if (hash.has("speed")) setSpeed(parseFloat(hash.get("speed")));
    ready = true;
    document.body.dataset.crtrajReady = "1";
    const loop = () => { if (playing()) refresh(); else if ($("crtraj-play").dataset.was === "1") refresh();
      $("crtraj-play").dataset.was = playing() ? "1" : "0"; requestAnimationFrame(loop); };
    requestAnimationFrame(loop);
  }
  function waitForScene(tries) { // meshcat applies its commands asynchronously (fetch of data: URLs)
    const expectClock = duration > 0 && !data.live; // a live page has no animation: it follows the newest step
    if (window.viewer && (!expectClock || hasClock())) { start(); return; }
    if (tries > 600) { start(); return; }
    setTimeout(() => waitForScene(tries + 1), 10);
  }
  $("crtraj-play").addEventListener("click", toggle);
  $("crtraj-prev").addEventListener("click", () => step(-1));
  $("crtraj-next").addEventListener("click", () => step(1));
  $("crtraj-speed").addEventListener("change", (ev) => setSpeed(parseFloat(ev.target.value)));
  document.addEventListener("keydown", (ev) => {
    if (ev.target && ev.target.tagName === "SELECT") return;
    const speeds = [0.25, 0.5, 1, 2, 4];
    const cur = speeds.indexOf(parseFloat($("crtraj-speed").value));
    const keys = { " ": toggle, ArrowLeft: () => step(-1), ArrowRight: () => step(1),
      "[": () => setSpeed(speeds[Math.max(0, cur - 1)]), "]": () => setSpeed(speeds[Math.min(4, cur + 1)]),
      Home: () => { pause(); seek(0); }, End: () => { pause(); seek(duration); },
      c: () => { if (runs.length) { pause(); seek(runs[0].closest_t); } } };
    if (keys[ev.key]) { ev.preventDefault(); keys[ev.key](); }
  });
  window.addEventListener("resize", () => { fitPane(); for (const p of plots) p.draw(); refresh(); });
  buildLegend(); buildEvents(); buildPlots(); refresh();
  // ------------------------------------------------------------ live: the served page of a running loop
  // The server (crtraj.viz.server) sends each frame of the run as one web-socket message: the transforms of every
  // moving node and the new steps' numbers (rows, appended as crtraj.viz.page.append_rows does). The panel follows
  // the newest step; plots and events are redrawn at most every PLOT_MS. A "crtraj_page" message means the data
  // changed as a whole: fetch it; when the run has ended (live false) the page reloads to its replay.
  const ROW_FIELDS = ["t", "status", "near", "tip_error", "iteration", "velocity", "acceleration"];
  const PLOT_MS = 250;
  let stale = false, lastBuild = 0;
  function rebuild() {
    plots.length = 0; $("crtraj-plots").innerHTML = ""; $("crtraj-events").innerHTML = "";
    buildEvents(); buildPlots(); lastBuild = performance.now(); stale = false;
  }
  function load(d) {
    data = d; runs = d.runs; duration = lastT();
    frames = runs.length && runs[0].t.length ? runs[0].t : [0];
    shownTime = duration;
    rebuild(); refresh();
  }
  // The data fetched is a snapshot the server made before some frames the page may already have: rows that come
  // while a fetch is under way wait for it and are appended to the snapshot (appendRows skips what it has), so a
  // slow answer never takes the page back to an older step. A notice during a fetch asks for one more.
  let fetching = false, refetch = false, pending = [];
  function fetchData() {
    if (fetching) { refetch = true; return; }
    fetching = true; refetch = false;
    fetch("data.json", { cache: "no-store" }).then((r) => r.json()).then((d) => {
      fetching = false;
      if (!d.live && data.live) { location.reload(); return; }
      if (d.live) load(d);
      if (refetch) { fetchData(); return; }
      const rows = pending; pending = [];
      rows.forEach(appendRows);
    }).catch(() => { fetching = false; setTimeout(fetchData, 1000); });
  }
  function appendRows(rows) {
    if (!data.live || !runs.length) return;
    if (fetching) { pending.push(rows); return; }
    const r = runs[0], n = r.t.length;
    if (rows.k > n) { pending.push(rows); fetchData(); return; } // a gap: frames came before this page's data
    const skip = n - rows.k;
    if (skip >= rows.t.length) return;
    const last = n ? r.t[n - 1] : -Infinity;
    for (const f of ROW_FIELDS) r[f].push(...rows[f].slice(skip));
    rows.clearance.forEach((c, i) => r.clearance[i].push(...c.slice(skip)));
    for (const e of rows.events) if (e.t > last) r.events.push(e);
    r.closest_t = rows.closest_t;
    if (rows.headline !== undefined) r.headline = rows.headline;
    duration = lastT(); frames = r.t; shownTime = duration;
    refresh();
    stale = true;
    if (performance.now() - lastBuild >= PLOT_MS) { rebuild(); refresh(); }
  }
  function applyFrame(cmd) {
    const m = cmd.matrices;
    cmd.paths.forEach((p, i) => window.viewer.set_transform(p.split("/").filter((s) => s), m.subarray(16 * i, 16 * i + 16)));
    window.viewer.set_dirty();
    if (cmd.rows) appendRows(cmd.rows);
  }
  if (window.viewer && window.viewer.handle_command) {
    const meshcatCommand = window.viewer.handle_command.bind(window.viewer);
    window.viewer.handle_command = (cmd) => {
      if (cmd.type === "crtraj_frame") applyFrame(cmd);
      else if (cmd.type === "crtraj_page") fetchData();
      else meshcatCommand(cmd);
    };
  }
  if (data.live) setInterval(() => { if (stale && performance.now() - lastBuild >= PLOT_MS) { rebuild(); refresh(); } }, PLOT_MS);
  if (data.live) shownTime = duration;
  window.crtrajView = { seek, play, pause, step, setSpeed, project, time: now, isReady: () => ready,
    get data() { return data; } };
  waitForScene(0);
})();
