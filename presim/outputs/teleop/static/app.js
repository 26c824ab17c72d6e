// PreSim teleop page: draws what the server sends, sends velocity / joint / button commands.
// Protocol: presim/outputs/teleop/protocol.py (client -> server) and server.py (server -> client).
"use strict";
(function () {
  const $ = (id) => document.getElementById(id);
  const T = {            // exposed as window.teleop for tests and measurements
    framesDrawn: 0, frameTimes: [], latencies: [], lags: [], messages: [], lastState: null, init: null,
    connected: false, clientId: null,
  };
  window.teleop = T;
  let ws = null, map = null, mapImg = null, traj = [], pending = null, teleportMode = false;
  const held = new Set();
  let cmdSeq = 0, lastSentZero = true, pressStart = null;   // pressStart: first command of a press from rest

  function show(kind, text) {
    const m = $("msg");
    m.className = "msg " + kind;
    m.textContent = text;
    T.messages.push({ kind, text });
    clearTimeout(show.t);
    show.t = setTimeout(() => { m.className = "msg"; m.textContent = ""; }, kind === "error" ? 8000 : 4000);
  }

  function send(obj) {
    if (ws && ws.readyState === 1) ws.send(JSON.stringify(obj));
  }
  T.send = send;
  T.sendRaw = (text) => { if (ws && ws.readyState === 1) ws.send(text); };

  // ---- velocity commands ----------------------------------------------------------------------
  const KEYMAP = { w: "w", arrowup: "w", s: "s", arrowdown: "s", a: "a", arrowleft: "a", d: "d",
                   arrowright: "d", q: "q", e: "e", r: "r", f: "f" };
  function command() {
    const k = (c) => (held.has(c) ? 1 : 0);
    const v = parseFloat($("speed").value);
    return { vx: v * (k("w") - k("s")), vy: 0.6 * v * (k("q") - k("e")), wz: 1.6 * v * (k("a") - k("d")),
             vz: 0.5 * v * (k("r") - k("f")) };
  }
  function sendCmd() {
    const c = command();
    const zero = !c.vx && !c.vy && !c.wz && !c.vz;
    if (zero && lastSentZero) return;
    cmdSeq += 1;
    send(Object.assign({ type: "cmd_vel", seq: cmdSeq }, c));
    lastSentZero = zero;
  }
  setInterval(sendCmd, 100);   // held keys keep the command alive (the server stops the robot after 0.5 s)
  function press(k) {
    if (held.has(k)) return;
    if (!held.size) pressStart = { seq: cmdSeq + 1, t: performance.now() };   // key-to-motion starts here
    held.add(k);
    sendCmd();
  }
  function release(k) { if (held.delete(k)) sendCmd(); }
  function stopAll() { held.clear(); lastSentZero = false; sendCmd(); }

  document.addEventListener("keydown", (ev) => {
    if (ev.target.tagName === "INPUT") return;
    const k = KEYMAP[ev.key.toLowerCase()];
    if (ev.key === " ") { stopAll(); ev.preventDefault(); return; }
    if (k) { press(k); ev.preventDefault(); }
  });
  document.addEventListener("keyup", (ev) => {
    const k = KEYMAP[ev.key.toLowerCase()];
    if (k) { release(k); ev.preventDefault(); }
  });
  window.addEventListener("blur", stopAll);
  document.querySelectorAll(".pad button[data-k]").forEach((b) => {
    const k = b.dataset.k;
    b.addEventListener("pointerdown", (ev) => { press(k); b.setPointerCapture(ev.pointerId); });
    b.addEventListener("pointerup", () => release(k));
    b.addEventListener("pointercancel", () => release(k));
  });
  $("stop").addEventListener("click", stopAll);
  $("speed").addEventListener("input", () => { $("speedv").textContent = $("speed").value; });
  $("speedv").textContent = $("speed").value;

  // ---- buttons --------------------------------------------------------------------------------
  $("reset").addEventListener("click", () => send({ type: "reset" }));
  $("snapshot").addEventListener("click", () => send({ type: "snapshot" }));
  $("take").addEventListener("click", () => send({ type: "take_control" }));
  $("record").addEventListener("click", () => {
    const on = !(T.lastState && T.lastState.recording);
    send({ type: "record", on });
  });
  $("teleport").addEventListener("click", () => {
    teleportMode = !teleportMode;
    $("teleport").classList.toggle("on", teleportMode);
  });
  $("map").addEventListener("click", (ev) => {
    if (!teleportMode || !map) return;
    const r = $("map").getBoundingClientRect();
    const sx = $("map").width / r.width, sy = $("map").height / r.height;
    const p = canvasToWorld((ev.clientX - r.left) * sx, (ev.clientY - r.top) * sy);
    send({ type: "teleport", x: p[0], y: p[1] });
    teleportMode = false;
    $("teleport").classList.remove("on");
  });

  function buildJoints(joints) {
    const box = $("joints");
    box.innerHTML = "";
    for (const j of joints) {
      const lo = isFinite(j.lower) ? j.lower : -3.14, hi = isFinite(j.upper) ? j.upper : 3.14;
      const lab = document.createElement("label");
      lab.innerHTML = `${j.name} <input type="range" min="${lo}" max="${hi}" step="0.01" value="0"> <span></span>`;
      const inp = lab.querySelector("input");
      inp.dataset.joint = j.name;
      inp.addEventListener("input", () => {
        lab.querySelector("span").textContent = (+inp.value).toFixed(2);
        send({ type: "joint", name: j.name, value: parseFloat(inp.value) });
      });
      box.appendChild(lab);
    }
  }

  // ---- drawing --------------------------------------------------------------------------------
  function worldToCanvas(x, y) {
    const c = $("map"), m = map;
    const s = Math.min(c.width / m.width, c.height / m.height);
    const ox = (c.width - m.width * s) / 2, oy = (c.height - m.height * s) / 2;
    const px = (x - m.origin_xy[0]) / m.resolution_m, py = m.height - (y - m.origin_xy[1]) / m.resolution_m;
    return [ox + px * s, oy + py * s, s / m.resolution_m];
  }
  function canvasToWorld(cx, cy) {
    const c = $("map"), m = map;
    const s = Math.min(c.width / m.width, c.height / m.height);
    const ox = (c.width - m.width * s) / 2, oy = (c.height - m.height * s) / 2;
    return [m.origin_xy[0] + ((cx - ox) / s) * m.resolution_m, m.origin_xy[1] + (m.height - (cy - oy) / s) * m.resolution_m];
  }
  function drawMap() {
    if (!map) return;
    const c = $("map"), g = c.getContext("2d");
    g.fillStyle = "#333"; g.fillRect(0, 0, c.width, c.height);
    if (mapImg) {
      const [x0, y0] = worldToCanvas(map.origin_xy[0], map.origin_xy[1] + map.height * map.resolution_m);
      const [x1, y1] = worldToCanvas(map.origin_xy[0] + map.width * map.resolution_m, map.origin_xy[1]);
      g.imageSmoothingEnabled = false;
      g.drawImage(mapImg, x0, y0, x1 - x0, y1 - y0);
    }
    if (traj.length > 1) {
      g.strokeStyle = "#ff5050"; g.lineWidth = 2; g.beginPath();
      traj.forEach((p, i) => { const q = worldToCanvas(p[0], p[1]); i ? g.lineTo(q[0], q[1]) : g.moveTo(q[0], q[1]); });
      g.stroke();
    }
    const s = T.lastState;
    if (!s) return;
    const cam = s.camera, [cx, cy, ppm] = worldToCanvas(cam.x, cam.y);
    const half = (cam.hfov_deg * Math.PI) / 360, len = 1.5 * ppm;
    g.fillStyle = "rgba(255,210,0,0.35)"; g.beginPath(); g.moveTo(cx, cy);
    g.lineTo(cx + len * Math.cos(cam.yaw + half), cy - len * Math.sin(cam.yaw + half));
    g.lineTo(cx + len * Math.cos(cam.yaw - half), cy - len * Math.sin(cam.yaw - half));
    g.closePath(); g.fill();
    const p = s.pose, [bx, by] = worldToCanvas(p.x, p.y), r = Math.max(4, 0.25 * ppm);
    g.fillStyle = s.contact ? "#ff3030" : "#30a0ff"; g.beginPath(); g.arc(bx, by, r, 0, 2 * Math.PI); g.fill();
    g.strokeStyle = "#fff"; g.lineWidth = 2; g.beginPath(); g.moveTo(bx, by);
    g.lineTo(bx + 2 * r * Math.cos(p.yaw), by - 2 * r * Math.sin(p.yaw)); g.stroke();
  }
  function drawTicks(maxM) {
    const t = $("ticks");
    t.innerHTML = "";
    const step = maxM > 6 ? 2 : maxM > 3 ? 1 : 0.5;
    for (let v = 0; v <= maxM + 1e-6; v += step) {
      const s = document.createElement("span");
      s.style.left = (100 * v) / maxM + "%";
      s.textContent = v.toFixed(step < 1 ? 1 : 0) + (v + step > maxM + 1e-6 ? " m" : "");
      t.appendChild(s);
    }
    $("depthrange").textContent = `(0–${maxM} m, black = no depth)`;
  }
  function drawColorbar() {
    const c = $("colorbar"), g = c.getContext("2d");
    // turbo, sampled coarsely (same map the server uses for the depth image)
    const turbo = [[48,18,59],[70,107,227],[40,187,236],[49,242,153],[162,252,60],[237,208,58],[251,128,34],[208,47,5],[122,4,3]];
    const grad = g.createLinearGradient(0, 0, c.width, 0);
    turbo.forEach((rgb, i) => grad.addColorStop(i / (turbo.length - 1), `rgb(${rgb})`));
    g.fillStyle = grad; g.fillRect(0, 0, c.width, c.height);
  }
  function status(s) {
    const rows = [
      ["steps/s", s.at_rest ? "0 (at rest: paused until a command)" : s.steps_per_s], ["render ms", s.render_ms], ["hole fraction", (100 * s.hole_fraction).toFixed(1) + " %"],
      ["collisions", s.collisions + (s.contact ? " (now)" : "")], ["outside capture", s.outside ? "yes" : "no"],
      ["page frames/s", fps().toFixed(1)], ["frame lag ms", T.lags.length ? T.lags[T.lags.length - 1].toFixed(0) : "–"], ["key→motion ms", T.latencies.length ? T.latencies[T.latencies.length - 1].toFixed(0) : "–"],
      ["pose", `x ${s.pose.x.toFixed(2)} y ${s.pose.y.toFixed(2)} yaw ${(s.pose.yaw * 57.2958).toFixed(0)}°`],
      ["sim time", s.sim_time_s.toFixed(1) + " s"], ["recording", s.recording || "off"], ["tabs", s.clients],
    ];
    $("status").innerHTML = rows.map((r) => `<tr><td>${r[0]}</td><td>${r[1]}</td></tr>`).join("");
    document.querySelectorAll("#joints input").forEach((inp) => {   // sliders follow the robot unless dragged
      const q = s.joints[inp.dataset.joint];
      if (q != null && document.activeElement !== inp) {
        inp.value = q;
        inp.parentElement.querySelector("span").textContent = q.toFixed(2);
      }
    });
    $("record").textContent = s.recording ? "Stop recording" : "Start recording";
    $("record").classList.toggle("on", !!s.recording);
    const me = s.driver === T.clientId;
    $("role").textContent = s.driver == null ? "nobody drives" : me ? "you drive" : `tab ${s.driver} drives`;
    $("role").className = "badge" + (me ? " ok" : "");
  }
  function fps() {
    const now = performance.now();
    while (T.frameTimes.length && now - T.frameTimes[0] > 2000) T.frameTimes.shift();
    return T.frameTimes.length / 2;
  }

  async function drawImages(state, colorBuf, depthBuf) {
    const [a, b] = await Promise.all([
      createImageBitmap(new Blob([colorBuf], { type: "image/jpeg" })),
      createImageBitmap(new Blob([depthBuf], { type: "image/jpeg" })),
    ]);
    for (const [id, bmp] of [["color", a], ["depth", b]]) {
      const c = $(id);
      if (c.width !== bmp.width || c.height !== bmp.height) { c.width = bmp.width; c.height = bmp.height; }
      c.getContext("2d").drawImage(bmp, 0, 0);
      bmp.close();
    }
    T.framesDrawn += 1;
    T.frameTimes.push(performance.now());
    T.lags.push(Date.now() - 1000 * state.wall_time_s);   // publish -> drawn (same machine, same clock)
    if (T.lags.length > 1000) T.lags.shift();
    T.lastImageStep = state.step;
  }

  async function onState(s, color, depth) {
    try {
      if (color && depth) await drawImages(s, color, depth);
    } catch (e) {
      show("error", "could not draw a frame: " + e);
    }
    T.lastState = s;
    // key-to-motion: keydown -> the first drawn frame of a step that applied that press's command
    if (pressStart && color && s.cmd_seq != null && s.cmd_seq >= pressStart.seq &&
        (s.applied[0] || s.applied[1] || s.applied[2])) {
      T.latencies.push(performance.now() - pressStart.t);
      pressStart = null;
    }
    const last = traj[traj.length - 1];
    if (!last || Math.hypot(last[0] - s.pose.x, last[1] - s.pose.y) > 0.01) traj.push([s.pose.x, s.pose.y]);
    if (traj.length > 20000) traj.shift();
    drawMap();
    status(s);
    send({ type: "ack", seq: s.seq });
  }

  // ---- connection -----------------------------------------------------------------------------
  function connect() {
    ws = new WebSocket(`ws://${location.host}/ws`);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { T.connected = true; $("conn").textContent = "connected"; $("conn").className = "badge ok"; };
    ws.onclose = () => {
      T.connected = false; $("conn").textContent = "disconnected (reload to retry)"; $("conn").className = "badge bad";
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") {
        const m = JSON.parse(ev.data);
        if (m.type === "state") {
          if (m.has_images) pending = { state: m, color: null, depth: null };
          else onState(m, null, null);
        } else if (m.type === "init") {
          T.init = m; T.clientId = m.client_id; map = m.map; traj = m.trajectory.slice();
          $("scene").textContent = `${m.scene} · ${m.robot} (${m.drive})`;
          buildJoints(m.joints);
          if (m.depth_max_m) drawTicks(m.depth_max_m);
          drawMap();
        } else if (m.type === "error") show("error", m.message);
        else if (m.type === "info") show("info", m.message);
        else if (m.type === "reset") traj = [];
        return;
      }
      const bytes = new Uint8Array(ev.data), kind = bytes[0], payload = ev.data.slice(5);
      if (kind === 3) {
        createImageBitmap(new Blob([payload], { type: "image/png" })).then((b) => { mapImg = b; drawMap(); });
      } else if (pending && kind === 1) pending.color = payload;
      else if (pending && kind === 2) {
        pending.depth = payload;
        const p = pending; pending = null;
        if (!$("ticks").childElementCount && p.state.depth_max_m) drawTicks(p.state.depth_max_m);
        onState(p.state, p.color, p.depth);
      }
    };
  }
  drawColorbar();
  connect();
})();
