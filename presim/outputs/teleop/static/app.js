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
  // The per-run token of the printed URL (?token=...): every request to the server carries it.
  const TOKEN = new URLSearchParams(location.search).get("token") || "";
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
                   arrowright: "d", q: "q", e: "e", r: "r", f: "f", i: "i", k: "k", u: "u", o: "o",
                   j: "j", l: "l" };
  const JOINT_KEYS = { i: ["head_tilt_joint", 1], k: ["head_tilt_joint", -1],     // i: tilt down
                       j: ["head_pan_joint", 1], l: ["head_pan_joint", -1] };     // j: pan left
  let dofs = ["vx", "wz"], free = false;
  function command() {
    const k = (c) => (held.has(c) ? 1 : 0);
    const v = parseFloat($("speed").value);
    const c = { vx: v * (k("w") - k("s")), vy: 0.6 * v * (k("q") - k("e")), wz: 1.6 * v * (k("a") - k("d")) };
    if (free) {   // the free rig's other axes (a mobile base has none: the server would ignore them)
      c.vz = 0.5 * v * (k("r") - k("f")); c.wy = 0.8 * v * (k("i") - k("k")); c.wx = 0.8 * v * (k("u") - k("o"));
    }
    return c;
  }
  // I/K tilt and J/L pan a mobile robot's head joints: each press moves the joint target one step
  function jointStep(key) {
    const [name, sign] = JOINT_KEYS[key] || [];
    const inp = name && document.querySelector(`#joints input[data-joint="${name}"]`);
    if (!inp) return false;
    const v = Math.min(+inp.max, Math.max(+inp.min, +inp.value + sign * 0.1));
    inp.value = v;
    inp.parentElement.querySelector("span").textContent = v.toFixed(2);
    send({ type: "joint", name, value: v });
    return true;
  }
  function sendCmd() {
    const c = command();
    const zero = !c.vx && !c.vy && !c.wz && !c.vz && !c.wy && !c.wx;
    if (zero && lastSentZero) return;
    cmdSeq += 1;
    send(Object.assign({ type: "cmd_vel", seq: cmdSeq }, c));
    lastSentZero = zero;
  }
  setInterval(sendCmd, 100);   // held keys keep the command alive (the server stops the robot after 0.5 s)
  function press(k) {
    if (held.has(k)) return;
    if (!free && JOINT_KEYS[k]) { jointStep(k); return; }
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
  $("copypose").addEventListener("click", () => send({ type: "pose" }));
  $("addpose").addEventListener("click", () => send({ type: "path", action: "add" }));
  $("recpath").addEventListener("click", () => {
    const on = !(T.lastState && T.lastState.path && T.lastState.path.recording);
    send({ type: "path", action: on ? "start" : "stop" });
  });
  $("savepath").addEventListener("click", () => send({ type: "path", action: "save" }));
  $("clearpath").addEventListener("click", () => send({ type: "path", action: "clear" }));
  function copyText(text) {   // clipboard where the browser allows it; the text box always shows it
    $("posebox").value = text;
    if (navigator.clipboard && window.isSecureContext) return navigator.clipboard.writeText(text).then(() => true, () => false);
    $("posebox").select();
    try { return Promise.resolve(document.execCommand("copy")); } catch (e) { return Promise.resolve(false); }
  }
  function download(name, text) {
    const a = document.createElement("a");
    a.href = URL.createObjectURL(new Blob([text], { type: "text/plain" }));
    a.download = name;
    document.body.appendChild(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 1000);
  }
  // the pad and the key hint show the robot's own degrees of freedom only
  function setupDofs(m) {
    dofs = m.dofs || dofs; free = !!m.free;
    const names = new Set((m.joints || []).map((j) => j.name));
    const has = { q: dofs.includes("vy"), e: dofs.includes("vy"), r: dofs.includes("vz"), f: dofs.includes("vz"),
                  i: free || names.has("head_tilt_joint"), k: free || names.has("head_tilt_joint"),
                  u: dofs.includes("wx"), o: dofs.includes("wx"),
                  j: !free && names.has("head_pan_joint"), l: !free && names.has("head_pan_joint") };
    document.querySelectorAll(".pad button[data-k]").forEach((b) => {
      if (b.dataset.k in has) b.style.visibility = has[b.dataset.k] ? "" : "hidden";   // keeps the grid
    });
    const parts = ["W/S or ↑/↓ drive", "A/D or ←/→ turn"];
    if (has.q) parts.push("Q/E strafe");
    if (has.r) parts.push("R/F up/down");
    if (has.i) parts.push(free ? "I/K tilt down/up" : "I/K head tilt");
    if (has.j) parts.push("J/L head pan");
    if (has.u) parts.push("U/O roll");
    $("hint").textContent = "Keys: " + parts.join(", ") + ", space stops.";
  }
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
    const caps = T.init && T.init.captures;
    if (caps && caps.length) {   // captured camera positions: magenta dots with a short viewing direction
      const [, , ppm0] = worldToCanvas(0, 0), len = Math.max(5, 0.12 * ppm0);
      g.strokeStyle = "rgba(255,80,255,0.9)"; g.fillStyle = "#ff50ff"; g.lineWidth = 1;
      for (const [x, y, yaw] of caps) {
        const [cx, cy] = worldToCanvas(x, y);
        g.beginPath(); g.arc(cx, cy, 2, 0, 2 * Math.PI); g.fill();
        g.beginPath(); g.moveTo(cx, cy); g.lineTo(cx + len * Math.cos(yaw), cy - len * Math.sin(yaw)); g.stroke();
      }
    }
    if (traj.length > 1) {
      g.strokeStyle = "#ff5050"; g.lineWidth = 2; g.beginPath();
      traj.forEach((p, i) => { const q = worldToCanvas(p[0], p[1]); i ? g.lineTo(q[0], q[1]) : g.moveTo(q[0], q[1]); });
      g.stroke();
    }
    const s = T.lastState;
    if (!s) return;
    const cam = s.camera, [cx, cy, ppm] = worldToCanvas(cam.x, cam.y);
    const half = (cam.hfov_deg * Math.PI) / 360, len = ((T.init && T.init.frustum_m) || 1.5) * ppm;
    g.fillStyle = "rgba(255,210,0,0.35)"; g.beginPath(); g.moveTo(cx, cy);
    g.lineTo(cx + len * Math.cos(cam.yaw + half), cy - len * Math.sin(cam.yaw + half));
    g.lineTo(cx + len * Math.cos(cam.yaw - half), cy - len * Math.sin(cam.yaw - half));
    g.closePath(); g.fill();
    const p = s.pose, [bx, by] = worldToCanvas(p.x, p.y);
    const r = Math.max(4, ((T.init && T.init.robot_radius_m) || 0.25) * ppm);
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
      ["camera", `z ${s.camera.z.toFixed(2)} m, tilt ${(s.camera.pitch * 57.2958).toFixed(0)}° (down +)`],
      ["camera path", `${s.path.poses} poses` + (s.path.recording ? " (recording)" : "")],
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
    $("recpath").textContent = s.path.recording ? "Stop path" : "Record path";
    $("recpath").classList.toggle("on", !!s.path.recording);
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
    ws = new WebSocket(`ws://${location.host}/ws?token=${encodeURIComponent(TOKEN)}`);
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
          setupDofs(m);
          if (m.depth_max_m) drawTicks(m.depth_max_m);
          drawMap();
        } else if (m.type === "pose") {
          T.pose = m;
          copyText(m.tum).then((ok) => show("info", (ok ? "copied: " : "pose (copy from the box): ") + m.tum));
        } else if (m.type === "path_saved") {
          T.pathSaved = m;
          download(m.name, m.tum);
          show("info", `camera path saved: ${m.path} (${m.poses} poses; downloaded as ${m.name}) — ` +
               `presim render SCENE --poses ${m.name}`);
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
