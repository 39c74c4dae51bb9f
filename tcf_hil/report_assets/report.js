/* tcf-hil run report: the map's zoom, layers and facts; the stem table; the 3D cloud.
   No library: everything the page needs is in the page. */
"use strict";
(function () {
  const D = JSON.parse(document.getElementById("tcf-data").textContent);
  const OUT = D.outcomes;
  const rows = D.stems.concat(D.sic);  // truth first, then the SIC's stems
  const nTruth = D.stems.length;

  // ------------------------------------------------------------------ formatting
  function esc(s) {
    return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));
  }
  function fmt(v, d) {
    if (v === null || v === undefined || v === "") return "–";
    if (typeof v === "number") return d === undefined ? String(v) : v.toFixed(d);
    return String(v);
  }
  function cm(v) { return v === null || v === undefined ? "–" : (100 * v).toFixed(1); }
  function label(outcome) { return OUT[outcome] ? OUT[outcome][0] : outcome; }

  function facts(r) {
    const t = [];
    if (r.source === "truth") {
      t.push(["tree", fmt(r.id)], ["outcome", label(r.outcome) + (r.why ? " — " + r.why : "")],
        ["class, true → SIC", fmt(r["class"]) + " → " + fmt(r.observed_class)],
        ["DBH, true → SIC", cm(r.dbh_m) + " → " + cm(r.observed_dbh_m) + " cm"],
        ["height, true → SIC", fmt(r.height_m, 1) + " → " + fmt(r.observed_height_m, 1) + " m"],
        ["SIC stem", fmt(r.matched_id)], ["position error", fmt(r.match_distance_m, 3) + " m"],
        ["from the track", fmt(r.distance_to_track_m, 1) + " m"], ["returns", fmt(r.returns)]);
      if (r.species) t.push(["species", r.species]);
      if (r.defects) t.push(["defects", r.defects]);
    } else {
      t.push(["SIC stem", fmt(r.id)], ["outcome", label(r.outcome)], ["class", fmt(r["class"])],
        ["DBH", cm(r.dbh_m) + " cm"], ["height", fmt(r.height_m, 1) + " m"],
        ["tree", fmt(r.matched_id)], ["position error", fmt(r.match_distance_m, 3) + " m"],
        ["from the track", fmt(r.distance_to_track_m, 1) + " m"]);
    }
    t.push(["x, y, z", [r.x, r.y, r.z].map((v) => fmt(v, 2)).join(", ") + " m"]);
    return "<table>" + t.map((p) => "<tr><td>" + esc(p[0]) + "</td><td><b>" + esc(p[1]) +
      "</b></td></tr>").join("") + "</table>";
  }

  // ------------------------------------------------------------------ the map
  const svg = document.getElementById("map-svg");
  const tip = document.getElementById("tip");
  const factsBox = document.getElementById("facts");
  const W0 = parseFloat(svg.dataset.w), H0 = parseFloat(svg.dataset.h);
  let vb = { x: 0, y: 0, w: W0, h: H0 };
  const truthEls = Array.from(svg.querySelectorAll("#truth-g circle"));
  const sicEls = Array.from(svg.querySelectorAll("#sic-g use"));
  const arrows = Array.from(svg.querySelectorAll("use.arrow"));
  const start = svg.querySelector("circle.start");

  function metresPerPixel() {
    const r = svg.getBoundingClientRect();
    return r.width > 0 ? Math.max(vb.w / r.width, vb.h / r.height) : vb.w / 800;
  }
  function restyle() {  // markers keep a size on screen as the view zooms
    const k = metresPerPixel();
    for (const c of truthEls) c.setAttribute("r", Math.max(parseFloat(c.dataset.r), 4.5 * k).toFixed(3));
    for (const u of sicEls) {
      const t = u.getAttribute("transform").replace(/ scale\([^)]*\)/, "");
      u.setAttribute("transform", t + " scale(" + (2.2 * k).toFixed(4) + ")");
    }
    for (const a of arrows) {
      const t = a.getAttribute("transform").replace(/ scale\([^)]*\)/, "");
      a.setAttribute("transform", t + " scale(" + (4.5 * k).toFixed(4) + ")");
    }
    if (start) start.setAttribute("r", (5 * k).toFixed(3));
  }
  function setView() {
    svg.setAttribute("viewBox", vb.x + " " + vb.y + " " + vb.w + " " + vb.h);
    restyle();
  }
  function toMap(e) {
    const p = svg.createSVGPoint();
    p.x = e.clientX; p.y = e.clientY;
    const m = svg.getScreenCTM();
    return m ? p.matrixTransform(m.inverse()) : { x: 0, y: 0 };
  }
  svg.addEventListener("wheel", (e) => {
    e.preventDefault();
    const p = toMap(e), f = e.deltaY > 0 ? 1.2 : 1 / 1.2;
    const w = Math.min(Math.max(vb.w * f, 2), W0 * 4), s = w / vb.w;
    vb = { x: p.x - (p.x - vb.x) * s, y: p.y - (p.y - vb.y) * s, w: w, h: vb.h * s };
    setView();
  }, { passive: false });
  let drag = null;
  svg.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, vb: Object.assign({}, vb), moved: false };
    svg.setPointerCapture(e.pointerId);
  });
  svg.addEventListener("pointermove", (e) => {
    if (drag) {
      const k = metresPerPixel();
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      if (Math.abs(dx) + Math.abs(dy) > 3) { drag.moved = true; svg.classList.add("dragging"); }
      vb.x = drag.vb.x - dx * k; vb.y = drag.vb.y - dy * k;
      svg.setAttribute("viewBox", vb.x + " " + vb.y + " " + vb.w + " " + vb.h);
      return;
    }
    const r = rowOf(e.target);
    if (!r) { tip.hidden = true; return; }
    const box = svg.parentNode.getBoundingClientRect();
    tip.innerHTML = facts(r);
    tip.hidden = false;
    const x = e.clientX - box.left + 14, y = e.clientY - box.top + 14;
    tip.style.left = Math.min(x, box.width - 250) + "px";
    tip.style.top = y + "px";
  });
  svg.addEventListener("pointerleave", () => { tip.hidden = true; });
  svg.addEventListener("pointerup", (e) => {
    const moved = drag && drag.moved;
    drag = null;
    svg.classList.remove("dragging");
    if (!moved) {
      const i = indexOf(e.target);
      if (i !== null) select(i, true);
    }
  });
  function indexOf(el) {
    if (el && el.dataset && el.dataset.i !== undefined) return parseInt(el.dataset.i, 10);
    if (el && el.dataset && el.dataset.j !== undefined) return nTruth + parseInt(el.dataset.j, 10);
    return null;
  }
  function rowOf(el) { const i = indexOf(el); return i === null ? null : rows[i]; }
  document.getElementById("map-reset").addEventListener("click", () => {
    vb = { x: 0, y: 0, w: W0, h: H0 }; setView();
  });
  for (const box of document.querySelectorAll("input[data-toggle]")) {
    const layer = svg.querySelector('[data-layer="' + box.dataset.toggle + '"]');
    if (!layer) { box.disabled = true; box.checked = false; continue; }
    box.addEventListener("change", () => { layer.style.display = box.checked ? "" : "none"; });
  }

  let selected = null;
  function elOf(i) { return i < nTruth ? truthEls[i] : sicEls[i - nTruth]; }
  function select(i, fromMap) {
    if (selected !== null) {
      const old = elOf(selected); if (old) old.classList.remove("sel");
      const tr = tbody.querySelector('tr[data-k="' + selected + '"]'); if (tr) tr.classList.remove("sel");
    }
    selected = i;
    const el = elOf(i); if (el) el.classList.add("sel");
    factsBox.innerHTML = facts(rows[i]);
    const tr = tbody.querySelector('tr[data-k="' + i + '"]');
    if (tr) { tr.classList.add("sel"); if (fromMap) tr.scrollIntoView({ block: "nearest" }); }
    if (!fromMap && el) {  // centre the map on it
      const cx = parseFloat(el.getAttribute("cx") || "NaN");
      const m = /translate\(([-\d.e]+),([-\d.e]+)\)/.exec(el.getAttribute("transform") || "");
      const x = isNaN(cx) ? (m ? parseFloat(m[1]) : null) : cx;
      const y = isNaN(cx) ? (m ? parseFloat(m[2]) : null) : parseFloat(el.getAttribute("cy"));
      if (x !== null) { vb.x = x - vb.w / 2; vb.y = y - vb.h / 2; setView(); }
    }
  }

  // ------------------------------------------------------------------ the stem table
  const COLS = [["source", "set"], ["id", "id"], ["outcome", "outcome"], ["why", "why"],
    ["class", "class"], ["observed_class", "SIC class"], ["dbh_m", "DBH, cm"],
    ["observed_dbh_m", "SIC DBH, cm"], ["height_m", "height, m"],
    ["observed_height_m", "SIC height, m"], ["match_distance_m", "position error, m"],
    ["distance_to_track_m", "from track, m"], ["returns", "returns"], ["matched_id", "matched"],
    ["species", "species"], ["defects", "defects"], ["x", "x"], ["y", "y"]];
  const CM = { dbh_m: 1, observed_dbh_m: 1 };
  const DEC = { height_m: 1, observed_height_m: 1, match_distance_m: 3, distance_to_track_m: 1, x: 2, y: 2 };
  const table = document.getElementById("stem-table");
  const thead = table.querySelector("thead"), tbody = table.querySelector("tbody");
  const filter = document.getElementById("stem-filter");
  for (const k of Object.keys(OUT)) {
    const n = rows.filter((r) => r.outcome === k).length;
    if (!n) continue;
    const o = document.createElement("option");
    o.value = k; o.textContent = label(k) + " (" + n + ")";
    filter.appendChild(o);
  }
  let sortKey = "id", sortDir = 1;
  thead.innerHTML = "<tr>" + COLS.map((c) => '<th data-key="' + c[0] + '">' + esc(c[1]) + "</th>").join("") + "</tr>";
  function cell(r, key) {
    const v = r[key];
    if (key === "outcome") return '<span style="color:' + OUT[v][1] + '">●</span> ' + esc(label(v));
    if (key in CM) return cm(v);
    if (key in DEC) return fmt(v, DEC[key]);
    return esc(fmt(v));
  }
  function shown() {
    const f = filter.value;
    const keys = [];
    for (let k = 0; k < rows.length; k++) if (!f || rows[k].outcome === f) keys.push(k);
    keys.sort((a, b) => {
      const x = rows[a][sortKey], y = rows[b][sortKey];
      const nx = x === null || x === undefined || x === "", ny = y === null || y === undefined || y === "";
      if (nx || ny) return nx === ny ? a - b : (nx ? 1 : -1);  // blanks last either way
      if (x < y) return -sortDir;
      if (x > y) return sortDir;
      return a - b;
    });
    return keys;
  }
  function render() {
    const keys = shown();
    tbody.innerHTML = keys.map((k) => '<tr data-k="' + k + '"' + (k === selected ? ' class="sel"' : "") + ">" +
      COLS.map((c) => "<td>" + cell(rows[k], c[0]) + "</td>").join("") + "</tr>").join("");
    for (const th of thead.querySelectorAll("th")) {
      if (th.dataset.key === sortKey) th.setAttribute("aria-sort", sortDir > 0 ? "ascending" : "descending");
      else th.removeAttribute("aria-sort");
    }
    document.getElementById("stem-count").textContent = keys.length + " of " + rows.length + " rows";
  }
  thead.addEventListener("click", (e) => {
    const th = e.target.closest("th"); if (!th) return;
    if (th.dataset.key === sortKey) sortDir = -sortDir; else { sortKey = th.dataset.key; sortDir = 1; }
    render();
  });
  tbody.addEventListener("click", (e) => {
    const tr = e.target.closest("tr"); if (tr) select(parseInt(tr.dataset.k, 10), false);
  });
  filter.addEventListener("change", render);
  document.getElementById("csv").addEventListener("click", () => {
    const q = (v) => {
      if (v === null || v === undefined) return "";
      const s = typeof v === "number" && !Number.isInteger(v) ? v.toFixed(4) : String(v);
      return /[",\n]/.test(s) ? '"' + s.replace(/"/g, '""') + '"' : s;
    };
    const lines = [D.columns.join(",")].concat(shown().map((k) => D.columns.map((c) => q(rows[k][c])).join(",")));
    const url = URL.createObjectURL(new Blob([lines.join("\n") + "\n"], { type: "text/csv" }));
    const a = document.createElement("a");
    a.href = url; a.download = "stems.csv";
    document.body.appendChild(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 1000);
  });
  render();
  setView();
  window.addEventListener("resize", restyle);

  // ------------------------------------------------------------------ the 3D cloud
  const cv = document.getElementById("cloud3d");
  const C = D.cloud;
  const ctx = cv.getContext("2d");
  if (!C) {
    ctx.fillStyle = "#10141a"; ctx.fillRect(0, 0, cv.width, cv.height);
    ctx.fillStyle = "#ccc"; ctx.font = "15px system-ui, sans-serif";
    ctx.fillText("No cloud in this run (see the note below).", 20, 40);
    return;
  }
  function bytes(b64) {
    const s = atob(b64), out = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out;
  }
  const n = C.n;
  const q = new Uint16Array(bytes(C.pos).buffer), cls = bytes(C.cls);
  const sid = new Uint16Array(bytes(C.sid).buffer);
  const P = new Float32Array(3 * n);
  for (let i = 0; i < 3 * n; i++) P[i] = q[i] * C.scale;
  // centre and size from the middle 96 % of the points: a few far returns must not shrink the view
  function quantile(a, f) {
    const v = [];
    for (let i = a; i < 3 * n; i += 3 * Math.max(1, Math.floor(n / 20000))) v.push(P[i]);
    v.sort((x, y) => x - y);
    return [v[Math.floor(f * (v.length - 1))], v[Math.floor((1 - f) * (v.length - 1))]];
  }
  const box = [0, 1, 2].map((a) => quantile(a, 0.02));
  const ctr = box.map((b) => (b[0] + b[1]) / 2);
  const ext = Math.max(box[0][1] - box[0][0], box[1][1] - box[1][0], box[2][1] - box[2][0], 1);
  for (let i = 0; i < n; i++) for (let a = 0; a < 3; a++) P[3 * i + a] -= ctr[a];

  function rgba(r, g, b) { return (255 << 24) | (b << 16) | (g << 8) | r; }  // little-endian ImageData
  function hsl(h, s, l) {
    const f = (k) => { const t = (k + h * 12) % 12; return l - s * Math.min(l, 1 - l) * Math.max(-1, Math.min(t - 3, 9 - t, 1)); };
    return rgba(Math.round(255 * f(0)), Math.round(255 * f(8)), Math.round(255 * f(4)));
  }
  const col = new Uint32Array(n);
  function colour(mode) {
    const zlo = box[2][0] - ctr[2], zr = box[2][1] - box[2][0] || 1;
    for (let i = 0; i < n; i++) {
      const h = Math.max(0, Math.min(1, (P[3 * i + 2] - zlo) / zr));
      if (mode === "height" || !C.labelled) {
        col[i] = hsl(0.7 - 0.7 * h, 0.85, 0.55);
      } else if (cls[i] === 64) {
        col[i] = hsl(((sid[i] * 0.6180339887) % 1), 0.8, 0.6);  // golden-ratio hues: neighbours differ
      } else if (cls[i] === 3 || cls[i] === 5) {
        col[i] = rgba(60, 150 + Math.round(60 * h), 70);
      } else if (cls[i] === 2) {
        const g = 95 + Math.round(80 * h); col[i] = rgba(g, g - 8, g - 25);
      } else if (cls[i] === 7) {
        col[i] = rgba(220, 220, 220);
      } else {
        col[i] = rgba(170, 130, 90);
      }
    }
  }
  let view = null;
  function resetView() { view = { yaw: -0.6, pitch: 0.55, dist: 1.25 * ext, px: 0, py: 0 }; }
  resetView();
  let size = 2;
  let img = null, buf = null, zb = null;
  function fit() {
    const r = cv.getBoundingClientRect();
    const w = Math.max(200, Math.min(1600, Math.round(r.width * (window.devicePixelRatio || 1))));
    const h = Math.round(w * 7 / 8);
    if (w !== cv.width || h !== cv.height || !img) {
      cv.width = w; cv.height = h;
      img = ctx.createImageData(w, h);
      buf = new Uint32Array(img.data.buffer);
      zb = new Float32Array(w * h);
    }
  }
  function draw() {
    fit();
    const w = cv.width, h = cv.height;
    buf.fill(rgba(16, 20, 26)); zb.fill(Infinity);
    const cy = Math.cos(view.yaw), sy = Math.sin(view.yaw);
    const cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    const f = h / (2 * Math.tan(0.45)), near = 0.05 * ext;
    const ox = w / 2 + view.px, oy = h / 2 + view.py, s = size;
    let drawn = 0;
    for (let i = 0; i < n; i++) {
      const x = P[3 * i], y = P[3 * i + 1], z = P[3 * i + 2];
      const right = cy * x + sy * y, fwd = -sy * x + cy * y;
      const up = z * cp + fwd * sp, depth = view.dist + fwd * cp - z * sp;
      if (depth < near) continue;
      const u = Math.round(ox + f * right / depth), v = Math.round(oy - f * up / depth);
      if (u < 0 || v < 0 || u + s > w || v + s > h) continue;
      for (let dv = 0; dv < s; dv++) {
        let k = (v + dv) * w + u;
        for (let du = 0; du < s; du++, k++) {
          if (depth < zb[k]) { zb[k] = depth; buf[k] = col[i]; }
        }
      }
      drawn++;
    }
    ctx.putImageData(img, 0, 0);
    cv.dataset.drawn = String(drawn);
  }
  let pending = false;
  function redraw() { if (!pending) { pending = true; requestAnimationFrame(() => { pending = false; draw(); }); } }
  let cd = null;
  cv.addEventListener("pointerdown", (e) => { cd = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 }; cv.setPointerCapture(e.pointerId); });
  cv.addEventListener("pointermove", (e) => {
    if (!cd) return;
    const dx = e.clientX - cd.x, dy = e.clientY - cd.y;
    cd.x = e.clientX; cd.y = e.clientY;
    if (cd.pan) { const k = cv.width / cv.getBoundingClientRect().width; view.px += dx * k; view.py += dy * k; }
    else { view.yaw += dx * 0.008; view.pitch = Math.max(-0.2, Math.min(1.5707, view.pitch + dy * 0.008)); }
    redraw();
  });
  cv.addEventListener("pointerup", () => { cd = null; });
  cv.addEventListener("contextmenu", (e) => e.preventDefault());
  cv.addEventListener("wheel", (e) => {
    e.preventDefault();
    view.dist = Math.max(0.05 * ext, Math.min(6 * ext, view.dist * (e.deltaY > 0 ? 1.15 : 1 / 1.15)));
    redraw();
  }, { passive: false });
  document.getElementById("cloud-colour").addEventListener("change", (e) => { colour(e.target.value); redraw(); });
  document.getElementById("cloud-size").addEventListener("change", (e) => { size = parseInt(e.target.value, 10); redraw(); });
  document.getElementById("cloud-reset").addEventListener("click", () => { resetView(); redraw(); });
  window.addEventListener("resize", redraw);
  colour("class");
  draw();
})();
