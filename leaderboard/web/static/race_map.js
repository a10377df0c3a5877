// Slipstream race map: a 2D player of a race's raw replay log (.replay.json.gz) beside the
// 3D viser replay. Every car is drawn at least MIN_CAR_PX long, the standings and lap counter
// follow the playback, "follow" zooms onto one car, and #t=12.3 in the page's address (the
// timeline's links) seeks to that moment. No inline script: the page's CSP forbids it.
"use strict";

(function () {
  const MIN_CAR_PX = 18; // a car is never drawn shorter than this, px
  const CAR_LENGTH = 0.58; // m (F1TENTH-sized), drawn to scale when zoomed in far enough
  const FOLLOW_SPAN = 5; // m of track visible on each side of the followed car

  const root = document.getElementById("race-map");
  if (!root) return;
  const canvas = root.querySelector("canvas");
  const ctx = canvas.getContext("2d");
  const clock = root.querySelector("[data-clock]");
  const standings = root.querySelector("[data-standings]");
  const playBtn = root.querySelector("[data-play]");
  const slider = root.querySelector("[data-seek]");
  const follow = root.querySelector("[data-follow]");
  const status = root.querySelector("[data-status]");

  let replay = null;
  let frame = 0;
  let playing = false;
  let lastTick = 0;

  async function loadJson(url) {
    const response = await fetch(url);
    if (!response.ok) throw new Error(`replay: HTTP ${response.status}`);
    const bytes = new Uint8Array(await response.arrayBuffer());
    let text;
    if (bytes[0] === 0x1f && bytes[1] === 0x8b) {
      const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
      text = await new Response(stream).text();
    } else {
      text = new TextDecoder().decode(bytes);
    }
    return JSON.parse(text);
  }

  // Cumulative progress (m along the centre line, unwrapped) of every car in every frame.
  function progressOf(doc) {
    const centre = doc.track.centre_line;
    const n = centre.length;
    const cum = [0];
    for (let i = 1; i < n; i++) {
      const dx = centre[i][0] - centre[i - 1][0];
      const dy = centre[i][1] - centre[i - 1][1];
      cum.push(cum[i - 1] + Math.hypot(dx, dy));
    }
    const last = centre[n - 1];
    const length = cum[n - 1] + Math.hypot(centre[0][0] - last[0], centre[0][1] - last[1]);
    const project = (x, y) => {
      let best = 0;
      let bestD = Infinity;
      for (let i = 0; i < n; i++) {
        const d = (centre[i][0] - x) ** 2 + (centre[i][1] - y) ** 2;
        if (d < bestD) { bestD = d; best = i; }
      }
      return cum[best];
    };
    const poses = doc.frames.poses;
    const nCars = doc.cars.length;
    const out = [];
    const prev = new Array(nCars).fill(null);
    const total = new Array(nCars).fill(0);
    for (let f = 0; f < poses.length; f++) {
      const row = [];
      for (let c = 0; c < nCars; c++) {
        const p = poses[f][c];
        if (p) {
          const s = project(p[0], p[1]);
          if (prev[c] === null) {
            total[c] = s > length / 2 ? s - length : s; // behind the line at the start
          } else {
            let ds = s - prev[c];
            if (ds > length / 2) ds -= length;
            if (ds < -length / 2) ds += length;
            total[c] += ds;
          }
          prev[c] = s;
        }
        row.push(total[c]);
      }
      out.push(row);
    }
    return out;
  }

  function colour(car) {
    const [r, g, b] = car.colour || [120, 120, 120];
    return `rgb(${r},${g},${b})`;
  }

  function bounds(doc) {
    const pts = doc.track.centre_line;
    let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
    for (const [x, y] of pts) {
      x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y);
    }
    const pad = 2.0;
    return [x0 - pad, y0 - pad, x1 + pad, y1 + pad];
  }

  function view() {
    const w = canvas.width;
    const h = canvas.height;
    let [x0, y0, x1, y1] = replay.bounds;
    const car = Number(follow.value);
    if (follow.value !== "" && replay.doc.frames.poses[frame][car]) {
      const [x, y] = replay.doc.frames.poses[frame][car];
      [x0, y0, x1, y1] = [x - FOLLOW_SPAN, y - FOLLOW_SPAN, x + FOLLOW_SPAN, y + FOLLOW_SPAN];
    }
    const scale = Math.min(w / (x1 - x0), h / (y1 - y0));
    const ox = (w - scale * (x1 - x0)) / 2 - scale * x0;
    const oy = (h + scale * (y1 - y0)) / 2 + scale * y0;
    return { scale, tx: (x) => ox + scale * x, ty: (y) => oy - scale * y };
  }

  function lapsAt(t) {
    const laps = new Array(replay.doc.cars.length).fill(0);
    const out = new Array(replay.doc.cars.length).fill(null);
    for (const e of replay.doc.events) {
      if (e.t > t + 1e-9) break;
      const c = replay.index[e.car];
      if (c === undefined) continue;
      if (e.type === "lap") laps[c] = e.lap;
      if (e.type === "finish") out[c] = "finished";
      if (e.type === "dnf") out[c] = `dnf (${e.reason})`;
    }
    return { laps, out };
  }

  function draw() {
    const doc = replay.doc;
    const v = view();
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.fillStyle = "#eef1f4";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    // the road: a thick line along the centre, as wide as the track
    const centre = doc.track.centre_line;
    const widths = doc.track.width_left.map((l, i) => l + doc.track.width_right[i]);
    ctx.lineJoin = "round";
    ctx.strokeStyle = "#9aa4ae";
    ctx.lineWidth = Math.max(2, v.scale * (widths.reduce((a, b) => a + b, 0) / widths.length));
    ctx.beginPath();
    centre.forEach(([x, y], i) => (i ? ctx.lineTo(v.tx(x), v.ty(y)) : ctx.moveTo(v.tx(x), v.ty(y))));
    ctx.closePath();
    ctx.stroke();
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 3;
    const [sx, sy] = centre[0];
    ctx.beginPath();
    ctx.arc(v.tx(sx), v.ty(sy), 4, 0, 2 * Math.PI);
    ctx.stroke();
    // the cars: a bright arrow at least MIN_CAR_PX long, labelled with the car's number
    const carLength = (doc.car && doc.car.length) || CAR_LENGTH; // m, from the replay
    const len = Math.max(MIN_CAR_PX, v.scale * carLength);
    doc.frames.poses[frame].forEach((p, c) => {
      if (!p) return;
      const [x, y, yaw] = p;
      ctx.save();
      ctx.translate(v.tx(x), v.ty(y));
      ctx.rotate(-yaw);
      ctx.fillStyle = colour(doc.cars[c]);
      ctx.strokeStyle = "#111820";
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      ctx.moveTo(len / 2, 0);
      ctx.lineTo(-len / 2, len * 0.3);
      ctx.lineTo(-len / 2, -len * 0.3);
      ctx.closePath();
      ctx.fill();
      ctx.stroke();
      ctx.restore();
      ctx.fillStyle = "#111820";
      ctx.font = "bold 12px system-ui, sans-serif";
      ctx.fillText(String(c), v.tx(x) + len * 0.55, v.ty(y) - len * 0.35);
    });
    canvas.dataset.carPx = String(Math.round(len));
    const t = doc.frames.t[frame];
    clock.textContent = `${t.toFixed(1)} s`;
    canvas.dataset.t = t.toFixed(2);
    slider.value = String(frame);
    // standings: out cars keep their finishing state, the rest by progress
    const { laps, out } = lapsAt(t);
    const order = doc.cars.map((_, c) => c).sort((a, b) => {
      const fa = out[a] === "finished" ? 0 : out[a] ? 2 : 1;
      const fb = out[b] === "finished" ? 0 : out[b] ? 2 : 1;
      if (fa !== fb) return fa - fb;
      return replay.progress[frame][b] - replay.progress[frame][a];
    });
    standings.replaceChildren(
      ...order.map((c, i) => {
        const li = document.createElement("li");
        const sw = document.createElement("span");
        sw.className = "swatch";
        sw.style.background = colour(doc.cars[c]);
        li.append(sw, `P${i + 1} ${doc.cars[c].name} · lap ${Math.min(laps[c] + 1, replay.laps)}/${replay.laps}`);
        if (out[c]) li.append(` · ${out[c]}`);
        return li;
      })
    );
  }

  function seek(t) {
    const ts = replay.doc.frames.t;
    let lo = 0;
    let hi = ts.length - 1;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (ts[mid] < t) lo = mid + 1; else hi = mid;
    }
    frame = lo;
    draw();
  }

  function tick(now) {
    if (!playing) return;
    const dt = (now - lastTick) / 1000;
    lastTick = now;
    const target = replay.doc.frames.t[frame] + dt;
    if (frame >= replay.doc.frames.t.length - 1) {
      playing = false;
      playBtn.textContent = "Play";
      return;
    }
    seek(target);
    requestAnimationFrame(tick);
  }

  function fromHash() {
    const m = /(?:^|[#&])t=([0-9.]+)/.exec(window.location.hash);
    if (m && replay) {
      playing = false;
      playBtn.textContent = "Play";
      seek(Number(m[1]));
      root.scrollIntoView({ block: "nearest" });
    }
  }

  async function start() {
    try {
      const doc = await loadJson(root.dataset.replay);
      replay = {
        doc,
        bounds: bounds(doc),
        progress: progressOf(doc),
        index: Object.fromEntries(doc.cars.map((c, i) => [c.agent, i])),
        laps: Number(root.dataset.laps) || 1,
      };
      slider.max = String(doc.frames.t.length - 1);
      doc.cars.forEach((c, i) => {
        const opt = document.createElement("option");
        opt.value = String(i);
        opt.textContent = `follow car ${i}: ${c.name}`;
        follow.append(opt);
      });
      status.textContent = "";
      root.dataset.ready = "1";
      draw();
      fromHash();
    } catch (err) {
      status.textContent = `The race map cannot be shown: ${err.message}`;
    }
  }

  playBtn.addEventListener("click", () => {
    if (!replay) return;
    playing = !playing;
    playBtn.textContent = playing ? "Pause" : "Play";
    if (playing) {
      if (frame >= replay.doc.frames.t.length - 1) frame = 0;
      lastTick = performance.now();
      requestAnimationFrame(tick);
    }
  });
  slider.addEventListener("input", () => {
    if (!replay) return;
    frame = Number(slider.value);
    draw();
  });
  follow.addEventListener("change", () => replay && draw());
  window.addEventListener("hashchange", fromHash);
  start();
})();
