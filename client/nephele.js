// Nephele browser client: plain JavaScript, no build step. See client/PROTOCOL.md.
//
// Flat screen: an orbit/fly camera driven by mouse, touch and keys; one view.
// WebXR immersive-vr: each eye's view and projection; the side-by-side video is split per eye.
// AR (the "display" choice, or WebXR immersive-ar): the composer paints the key colour where
// no object is; in immersive-ar the page keys it out, so the headset's view of the room shows.
// Either way the pose goes to the composer over the `control` data channel every 20 ms.
'use strict';

(() => {
  const POSE_INTERVAL_MS = 20;
  const PING_INTERVAL_MS = 1000;
  const POSE_MAGIC = 0x50;
  const POSE_VERSION = 1;
  const MODE_FLAT = 0;
  const MODE_XR = 1;
  const MODE_QUILT = 2;
  const MODE_AR = 3;
  // The light-field display's quilt (Looking Glass's 45-view layout): 5 columns, 9 rows, views
  // of aspect 0.75 spread over a 40-degree view cone (nephele_geometry::camera::QUILT_VIEW_CONE_DEG); view 0 (leftmost camera) bottom left.
  // The composer packs views row by row from the top in 5 columns
  // (nephele_proto::pose::grid_columns), so the pose lists them top row first.
  const QUILT = { views: 45, columns: 5, rows: 9, viewWidth: 180, viewHeight: 240, viewConeDeg: 40 };
  // The AR mode's key colour (sRGB, 0..1), as nephele_proto::pose::AR_KEY_SRGB.
  const AR_KEY = [0, 1, 0];

  // ---------------------------------------------------------------- small matrix helpers
  // Column-major 4x4 matrices in Float32Array(16), as WebGL and WebXR use.
  const mat4 = {
    multiply(a, b) {
      const out = new Float32Array(16);
      for (let c = 0; c < 4; c++) {
        for (let r = 0; r < 4; r++) {
          let s = 0;
          for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
          out[c * 4 + r] = s;
        }
      }
      return out;
    },
    // World-to-camera matrix of a camera at `eye` looking at `target` with `up` (OpenGL camera).
    lookAt(eye, target, up) {
      const f = normalize(sub(target, eye));
      const r = normalize(cross(f, up));
      const u = cross(r, f);
      return new Float32Array([
        r[0], u[0], -f[0], 0,
        r[1], u[1], -f[1], 0,
        r[2], u[2], -f[2], 0,
        -dot(r, eye), -dot(u, eye), dot(f, eye), 1,
      ]);
    },
    perspective(fovY, aspect, near, far) {
      const f = 1 / Math.tan(fovY / 2);
      return new Float32Array([
        f / aspect, 0, 0, 0,
        0, f, 0, 0,
        0, 0, (far + near) / (near - far), -1,
        0, 0, (2 * far * near) / (near - far), 0,
      ]);
    },
  };
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const normalize = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };

  // WebXR reference spaces are +Y up; Nephele's world is +Z up (client/PROTOCOL.md). This maps
  // a Nephele world point into the XR space, placing the scene origin 1.5 m in front of the
  // user at 1.1 m height: x -> x, y -> -z, z -> y, then a translation.
  const XR_FROM_NEPHELE = new Float32Array([
    1, 0, 0, 0,
    0, 0, -1, 0,
    0, 1, 0, 0,
    0, 1.1, -1.5, 1,
  ]);

  // ---------------------------------------------------------------- orbit / fly camera
  class OrbitCamera {
    constructor() { this.reset({ eye: [0, -4, 2], target: [0, 0, 0.5], fov_y_deg: 40 }); }
    reset(view) {
      this.home = view;
      this.target = view.target.slice();
      const d = sub(view.eye, view.target);
      this.radius = Math.max(1e-3, Math.hypot(d[0], d[1], d[2]));
      this.azimuth = Math.atan2(d[1], d[0]);
      this.elevation = Math.asin(Math.max(-1, Math.min(1, d[2] / this.radius)));
      this.fovY = (view.fov_y_deg * Math.PI) / 180;
    }
    eye() {
      const ce = Math.cos(this.elevation);
      return add(this.target, scale([ce * Math.cos(this.azimuth), ce * Math.sin(this.azimuth), Math.sin(this.elevation)], this.radius));
    }
    orbit(dAz, dEl) {
      this.azimuth += dAz;
      this.elevation = Math.max(-1.55, Math.min(1.55, this.elevation + dEl));
    }
    zoom(factor) { this.radius = Math.max(0.05, Math.min(1000, this.radius * factor)); }
    // Moves the target (and so the eye) in the camera's frame: right, forward, up.
    move(right, forward, up) {
      const f = normalize(sub(this.target, this.eye()));
      const r = normalize(cross(f, [0, 0, 1]));
      const delta = add(add(scale(r, right), scale(f, forward)), [0, 0, up]);
      this.target = add(this.target, scale(delta, this.radius));
    }
    view() { return mat4.lookAt(this.eye(), this.target, [0, 0, 1]); }
    projection(aspect) { return mat4.perspective(this.fovY, aspect, 0.05, 1000); }
  }

  // ---------------------------------------------------------------- the client
  const $ = (id) => document.getElementById(id);
  const params = new URLSearchParams(location.search);

  const client = {
    state: 'idle',
    sessionId: null,
    token: null,
    pc: null,
    channel: null,
    camera: new OrbitCamera(),
    views: 1,
    width: 640,
    height: 480,
    sequence: 0,
    posesSent: 0,
    rttMs: null,
    poseToFrameMs: null, // from the composer's 'frame' messages: pose sent -> its frame out
    xrSession: null,
    xrAr: false, // the XR session is immersive-ar
    xrEyeSize: null, // {width, height} the headset recommends per eye
    xrViews: null, // latest [{view, projection}] from the XR frame loop
    reconnectDelayMs: 1000,
    reconnecting: false, // the next connection resumes a lost one: keep the camera
    wantConnected: false,
    timers: [],
  };
  window.nephele = client; // for tests and the console

  function setState(state) {
    client.state = state;
    $('state').textContent = state;
  }

  async function fetchConfig() {
    try {
      const response = await fetch('v1/config');
      if (!response.ok) return { ice_servers: [], scenes: ['default'] };
      return await response.json();
    } catch (_) {
      return { ice_servers: [], scenes: ['default'] };
    }
  }

  function waitForIceGathering(pc, timeoutMs) {
    if (pc.iceGatheringState === 'complete') return Promise.resolve();
    return new Promise((resolve) => {
      const done = () => { pc.removeEventListener('icegatheringstatechange', check); resolve(); };
      const check = () => { if (pc.iceGatheringState === 'complete') done(); };
      pc.addEventListener('icegatheringstatechange', check);
      setTimeout(done, timeoutMs);
    });
  }

  // The stream's size per view: in VR the headset's recommended size per eye (its WebXR
  // layer's framebuffer, halved across); else `?width=&height=`, else the size chosen, where
  // 'window' is the stage in device pixels. Even sides (H.264 4:2:0), at most MAX_STREAM_SIDE.
  const MAX_STREAM_SIDE = 1920;
  function streamSize() {
    const fitted = (width, height) => {
      const scale = Math.min(1, MAX_STREAM_SIDE / Math.max(width, height, 1));
      const even = (n) => Math.max(2, 2 * Math.floor((n * scale) / 2));
      return [even(width), even(height)];
    };
    if (client.xrSession && client.xrEyeSize) return fitted(client.xrEyeSize.width, client.xrEyeSize.height);
    const choice = $('size').value;
    let [w, h] = choice.split('x').map(Number);
    if (choice === 'window') {
      const ratio = window.devicePixelRatio || 1;
      [w, h] = fitted($('stage').clientWidth * ratio, $('stage').clientHeight * ratio);
    }
    return [Number(params.get('width')) || w, Number(params.get('height')) || h];
  }

  async function connect() {
    client.wantConnected = true;
    [client.width, client.height] = streamSize();
    const quilt = !client.xrSession && $('display').value === 'quilt';
    client.views = client.xrSession ? 2 : quilt ? QUILT.views : 1;
    if (quilt) [client.width, client.height] = [QUILT.viewWidth, QUILT.viewHeight];
    $('quilt-info').hidden = !quilt;
    setState('connecting');
    $('connect').disabled = true;
    $('disconnect').disabled = false;
    const config = await fetchConfig();
    const pc = new RTCPeerConnection({ iceServers: (config.ice_servers || []).map(normaliseIceServer) });
    client.pc = pc;
    pc.addTransceiver('video', { direction: 'recvonly' });
    const channel = pc.createDataChannel('control', { ordered: false, maxRetransmits: 0 });
    channel.binaryType = 'arraybuffer';
    client.channel = channel;
    channel.onmessage = (event) => onControlMessage(event.data);
    channel.onopen = () => setState('streaming');
    channel.onclose = () => scheduleReconnect('data channel closed');
    pc.ontrack = (event) => {
      const video = $('video');
      // The element keeps the session's picture size: on a narrow link the composer sends a
      // smaller picture (its resolution follows its bitrate), which is scaled back up here
      // rather than shown smaller. A headset's layer samples the video as a texture anyway.
      const [columns, rows] = packing();
      [video.width, video.height] = [columns * client.width, rows * client.height];
      video.srcObject = event.streams[0] || new MediaStream([event.track]);
      video.play().catch(() => {});
    };
    pc.onconnectionstatechange = () => {
      if (pc.connectionState === 'failed') scheduleReconnect('peer connection failed');
      if (pc.connectionState === 'disconnected') {
        // Often recovers by itself; give it three seconds.
        setTimeout(() => { if (client.pc === pc && pc.connectionState === 'disconnected') scheduleReconnect('peer disconnected'); }, 3000);
      }
    };
    await pc.setLocalDescription(await pc.createOffer());
    await waitForIceGathering(pc, 2000);
    let response;
    try {
      // An invitation link (`?invite=...`) opens a master that requires one.
      const headers = { 'content-type': 'application/json' };
      if (params.get('invite')) headers.authorization = `Bearer ${params.get('invite')}`;
      response = await fetch('v1/sessions', {
        method: 'POST',
        headers,
        body: JSON.stringify({
          sdp: pc.localDescription.sdp,
          scene: params.get('scene') || $('scene').value,
          views: client.views,
          width: client.width,
          height: client.height,
          target_fps: Number(params.get('fps')) || 30,
        }),
      });
    } catch (error) {
      scheduleReconnect(`master unreachable: ${error}`);
      return;
    }
    if (response.status === 503 || response.status === 429) {
      const retry = Number(response.headers.get('retry-after')) || 2;
      setState(response.status === 503 ? `farm busy, retrying in ${retry} s` : `too many requests, retrying in ${retry} s`);
      teardown(false);
      client.timers.push(setTimeout(() => { if (client.wantConnected) connect(); }, retry * 1000));
      return;
    }
    const body = await response.json().catch(() => ({ error: `HTTP ${response.status}` }));
    if (!response.ok) {
      setState(`error: ${body.error || response.status}`);
      teardown(false);
      $('connect').disabled = false;
      return;
    }
    client.sessionId = body.session_id;
    client.token = body.token;
    $('session').textContent = body.session_id;
    // A reconnection (the composer restarted, the link dropped) keeps the user's camera where it
    // was; a new connection starts from the scene's suggested view.
    if (body.view && !client.reconnecting) client.camera.reset(body.view);
    client.reconnecting = false;
    await pc.setRemoteDescription({ type: 'answer', sdp: body.sdp });
    client.reconnectDelayMs = 1000;
    client.timers.push(setInterval(sendPose, POSE_INTERVAL_MS));
    client.timers.push(setInterval(sendPing, PING_INTERVAL_MS));
    client.timers.push(setInterval(updateStats, 1000));
    watchSession(body.session_id, body.token);
  }

  // Long poll on the session (`GET v1/sessions/{id}/watch`): the master answers
  // {"state": "ended"} the moment the service ends it (its composer died), so the page connects
  // again at once rather than after ICE's timeout and the grace above; {"state": "open"} after
  // a while means it lives (ask again).
  async function watchSession(id, token) {
    while (client.sessionId === id) {
      let state = null;
      try {
        const response = await fetch(`v1/sessions/${encodeURIComponent(id)}/watch`, {
          headers: { authorization: `Bearer ${token}` },
        });
        if (response.ok) state = (await response.json()).state;
        else await response.body?.cancel().catch(() => {});
      } catch (error) {
        state = null; // the master is unreachable: the peer connection's own checks decide
      }
      if (client.sessionId !== id) return;
      if (state === 'ended') {
        scheduleReconnect('the service ended the session', true);
        return;
      }
      if (state !== 'open') await new Promise((resolve) => setTimeout(resolve, 2000));
    }
  }

  function normaliseIceServer(server) {
    const out = { urls: server.urls };
    if (server.username) out.username = server.username;
    if (server.credential) out.credential = server.credential;
    return out;
  }

  function teardown(sendDelete) {
    for (const timer of client.timers) { clearInterval(timer); clearTimeout(timer); }
    client.timers = [];
    if (client.channel) { client.channel.onclose = null; client.channel.close(); }
    if (client.pc) { client.pc.onconnectionstatechange = null; client.pc.close(); }
    if (sendDelete && client.sessionId) {
      fetch(`v1/sessions/${encodeURIComponent(client.sessionId)}`, {
        method: 'DELETE',
        headers: { authorization: `Bearer ${client.token}` },
        keepalive: true,
      }).catch(() => {});
    }
    client.pc = null;
    client.channel = null;
    client.sessionId = null;
    client.token = null;
  }

  function disconnect() {
    client.wantConnected = false;
    client.reconnecting = false;
    teardown(true);
    setState('idle');
    $('connect').disabled = false;
    $('disconnect').disabled = true;
    $('session').textContent = '-';
  }

  // `gone`: the master already ended the session (nothing to DELETE).
  function scheduleReconnect(reason, gone = false) {
    if (!client.wantConnected) return;
    teardown(!gone);
    const delay = client.reconnectDelayMs;
    client.reconnectDelayMs = Math.min(10000, delay * 2);
    setState(`reconnecting in ${(delay / 1000).toFixed(0)} s (${reason})`);
    client.reconnecting = true;
    client.timers.push(setTimeout(() => { if (client.wantConnected) connect(); }, delay));
  }

  // ---------------------------------------------------------------- poses and control
  function currentViews() {
    if (client.xrSession && client.xrViews) return client.xrViews;
    if (client.views === QUILT.views) return quiltViews();
    const aspect = client.width / client.height;
    return [{ view: client.camera.view(), projection: client.camera.projection(aspect) }];
  }

  // The pose's display mode: immersive VR, AR (immersive-ar, or the page's AR choice), the
  // light-field quilt, or flat.
  function displayMode() {
    if (client.xrSession) return client.xrAr ? MODE_AR : MODE_XR;
    return { ar: MODE_AR, quilt: MODE_QUILT }[$('display').value] ?? MODE_FLAT;
  }

  // The quilt's views in the order the composer packs them (top row first, left to right):
  // cameras parallel to the orbit camera, spread along its right axis so that the orbit
  // target's plane (the focal plane) projects to the same pixels in every view, as
  // nephele_geometry::camera::quilt_rig does: view k sits at (k / (N - 1) - 1/2) * 2 tan(cone / 2)
  // focal distances, its principal point shifted by the same fraction of the focal length.
  function quiltViews() {
    const camera = client.camera;
    const eye = camera.eye();
    const forward = normalize(sub(camera.target, eye));
    const right = normalize(cross(forward, [0, 0, 1]));
    const halfExtent = Math.tan((QUILT.viewConeDeg * Math.PI) / 360);
    const aspect = QUILT.viewWidth / QUILT.viewHeight;
    const views = [];
    for (let row = 0; row < QUILT.rows; row++) {
      for (let column = 0; column < QUILT.columns; column++) {
        const k = (QUILT.rows - 1 - row) * QUILT.columns + column;
        const relative = (k / (QUILT.views - 1) - 0.5) * 2 * halfExtent;
        const shift = scale(right, relative * camera.radius);
        const view = mat4.lookAt(add(eye, shift), add(camera.target, shift), [0, 0, 1]);
        const projection = camera.projection(aspect);
        projection[8] = -projection[0] * relative;
        views.push({ view, projection });
      }
    }
    return views;
  }

  function encodePose(views, mode) {
    const buffer = new ArrayBuffer(20 + 128 * views.length);
    const data = new DataView(buffer);
    data.setUint8(0, POSE_MAGIC);
    data.setUint8(1, POSE_VERSION);
    data.setUint8(2, views.length);
    data.setUint8(3, mode);
    data.setUint32(4, client.sequence >>> 0, true);
    data.setFloat64(8, performance.now(), true);
    data.setUint16(16, client.width, true);
    data.setUint16(18, client.height, true);
    let offset = 20;
    for (const v of views) {
      for (let i = 0; i < 16; i++, offset += 4) data.setFloat32(offset, v.view[i], true);
      for (let i = 0; i < 16; i++, offset += 4) data.setFloat32(offset, v.projection[i], true);
    }
    return buffer;
  }

  function sendPose() {
    const channel = client.channel;
    if (!channel || channel.readyState !== 'open') return;
    const views = currentViews();
    if (views.length !== client.views) return; // the session was opened for another view count
    channel.send(encodePose(views, displayMode()));
    client.sequence = (client.sequence + 1) >>> 0;
    client.posesSent += 1;
  }

  let pingId = 0;
  function sendPing() {
    const channel = client.channel;
    if (channel && channel.readyState === 'open') {
      channel.send(JSON.stringify({ type: 'ping', id: ++pingId, t: performance.now() }));
    }
  }

  function onControlMessage(data) {
    if (typeof data !== 'string') return;
    let message;
    try { message = JSON.parse(data); } catch (_) { return; }
    if (message.type === 'pong' && typeof message.t === 'number') {
      client.rttMs = performance.now() - message.t;
      $('rtt').textContent = `${client.rttMs.toFixed(1)} ms`;
    } else if (message.type === 'frame' && typeof message.t === 'number') {
      client.poseToFrameMs = performance.now() - message.t;
    }
  }

  // Frame rate and bitrate from the receiver's statistics (getStats), once a second.
  let lastStats = null;
  async function updateStats() {
    if (!client.pc) return;
    const report = await client.pc.getStats();
    report.forEach((s) => {
      if (s.type !== 'inbound-rtp' || s.kind !== 'video') return;
      client.framesDecoded = s.framesDecoded;
      if (lastStats) {
        const seconds = (s.timestamp - lastStats.timestamp) / 1000;
        if (seconds > 0) {
          $('fps').textContent = ((s.framesDecoded - lastStats.framesDecoded) / seconds).toFixed(1);
          const [columns, rows] = packing();
          const smaller = s.frameWidth && s.frameWidth < columns * client.width ? ` at ${s.frameWidth}x${s.frameHeight}` : '';
          $('bitrate').textContent = formatBitrate((8 * (s.bytesReceived - lastStats.bytesReceived)) / seconds) + smaller;
        }
      }
      lastStats = { timestamp: s.timestamp, framesDecoded: s.framesDecoded, bytesReceived: s.bytesReceived };
    });
    if (client.poseToFrameMs !== null) $('latency').textContent = `${client.poseToFrameMs.toFixed(0)} ms`;
  }

  // Views per row and rows of the stream's picture (the composer's packing).
  function packing() {
    if (client.views === 1) return [1, 1];
    if (client.views === 2) return [2, 1];
    return [QUILT.columns, QUILT.rows];
  }

  // An unchanging picture encodes to a few kbit/s: in Mbit/s with two decimals it read 0.00.
  function formatBitrate(bitsPerSecond) {
    if (bitsPerSecond >= 1e6) return `${(bitsPerSecond / 1e6).toFixed(2)} Mbit/s`;
    return `${(bitsPerSecond / 1e3).toFixed(1)} kbit/s`;
  }

  // ---------------------------------------------------------------- input
  function installInput() {
    const stage = $('stage');
    let drag = null;
    stage.addEventListener('contextmenu', (e) => e.preventDefault());
    stage.addEventListener('pointerdown', (e) => {
      stage.setPointerCapture(e.pointerId);
      drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2, pointers: (drag?.pointers || 0) + 1 };
    });
    stage.addEventListener('pointermove', (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x;
      const dy = e.clientY - drag.y;
      drag.x = e.clientX;
      drag.y = e.clientY;
      if (drag.pan) client.camera.move(-dx * 0.002, 0, dy * 0.002);
      else client.camera.orbit(-dx * 0.008, dy * 0.008);
    });
    const end = () => { drag = null; };
    stage.addEventListener('pointerup', end);
    stage.addEventListener('pointercancel', end);
    stage.addEventListener('wheel', (e) => { e.preventDefault(); client.camera.zoom(Math.exp(e.deltaY * 0.001)); }, { passive: false });
    // Pinch zoom with two fingers.
    let pinch = null;
    stage.addEventListener('touchmove', (e) => {
      if (e.touches.length !== 2) { pinch = null; return; }
      const d = Math.hypot(e.touches[0].clientX - e.touches[1].clientX, e.touches[0].clientY - e.touches[1].clientY);
      if (pinch) client.camera.zoom(pinch / d);
      pinch = d;
    }, { passive: true });
    stage.addEventListener('touchend', () => { pinch = null; });
    const step = 0.05;
    window.addEventListener('keydown', (e) => {
      if (e.target instanceof HTMLSelectElement) return;
      switch (e.key) {
        case 'w': client.camera.move(0, step, 0); break;
        case 's': client.camera.move(0, -step, 0); break;
        case 'a': client.camera.move(-step, 0, 0); break;
        case 'd': client.camera.move(step, 0, 0); break;
        case 'q': client.camera.move(0, 0, -step); break;
        case 'e': client.camera.move(0, 0, step); break;
        case 'ArrowLeft': client.camera.orbit(0.1, 0); break;
        case 'ArrowRight': client.camera.orbit(-0.1, 0); break;
        case 'ArrowUp': client.camera.orbit(0, 0.1); break;
        case 'ArrowDown': client.camera.orbit(0, -0.1); break;
        case 'r': client.camera.reset(client.camera.home); break;
        default: return;
      }
      e.preventDefault();
    });
  }

  // ---------------------------------------------------------------- WebXR
  // The composer packs the two eyes side by side; each eye's viewport shows its half of the
  // video, drawn as a textured quad with WebGL.
  async function setupXr() {
    if (!navigator.xr) return;
    const offered = async (mode) => {
      try { return await navigator.xr.isSessionSupported(mode); } catch (_) { return false; }
    };
    for (const [mode, id] of [['immersive-vr', 'enter-vr'], ['immersive-ar', 'enter-ar']]) {
      if (!(await offered(mode))) continue;
      const button = $(id);
      button.hidden = false;
      button.onclick = () => (client.xrSession ? client.xrSession.end() : enterXr(mode));
    }
  }

  async function enterXr(mode) {
    const ar = mode === 'immersive-ar';
    const session = await navigator.xr.requestSession(mode, { optionalFeatures: ['local-floor'] });
    const canvas = $('xr-canvas');
    const gl = canvas.getContext('webgl', { xrCompatible: true, alpha: true, premultipliedAlpha: true });
    await gl.makeXRCompatible();
    const layer = new XRWebGLLayer(session, gl);
    session.updateRenderState({ baseLayer: layer });
    // Both eyes side by side in the layer's framebuffer, sized as the headset recommends.
    client.xrEyeSize = { width: layer.framebufferWidth / 2, height: layer.framebufferHeight };
    const space = await session.requestReferenceSpace('local-floor').catch(() => session.requestReferenceSpace('local'));
    const drawer = makeVideoDrawer(gl, ar);
    client.xrSession = session;
    client.xrAr = ar;
    const button = $(ar ? 'enter-ar' : 'enter-vr');
    button.textContent = ar ? 'Exit AR' : 'Exit VR';
    // A new session with two views (the stream size changes).
    disconnect();
    connect();
    session.addEventListener('end', () => {
      client.xrSession = null;
      client.xrViews = null;
      client.xrAr = false;
      button.textContent = ar ? 'Enter AR' : 'Enter VR';
      disconnect();
      connect();
    });
    const onFrame = (time, frame) => {
      session.requestAnimationFrame(onFrame);
      const pose = frame.getViewerPose(space);
      if (!pose) return;
      const layer = session.renderState.baseLayer;
      gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
      // Transparent where nothing is drawn: in immersive-ar the room shows through.
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
      drawer.upload($('video'));
      client.xrViews = pose.views.slice(0, 2).map((view) => ({
        view: mat4.multiply(view.transform.inverse.matrix, XR_FROM_NEPHELE),
        projection: new Float32Array(view.projectionMatrix),
      }));
      pose.views.slice(0, 2).forEach((view, eye) => {
        const vp = layer.getViewport(view);
        gl.viewport(vp.x, vp.y, vp.width, vp.height);
        drawer.draw(eye, 2);
      });
    };
    session.requestAnimationFrame(onFrame);
  }

  // Draws one view's part of the video. With `keyed` (AR), the key colour becomes transparent:
  // coverage from the distance to the key (premultiplied output; the video's compression
  // smears the key a little, hence the soft ramp), and the key's green spilled into partly
  // covered pixels taken back out.
  function makeVideoDrawer(gl, keyed) {
    const vs = 'attribute vec2 p; uniform vec2 u; varying vec2 t; void main(){ t = vec2(u.x + (p.x*0.5+0.5)*u.y, 0.5-p.y*0.5); gl_Position = vec4(p,0.,1.); }';
    const key = `vec3(${AR_KEY.map((v) => v.toFixed(1)).join(',')})`;
    const fs = keyed
      ? `precision mediump float; varying vec2 t; uniform sampler2D s; void main(){ vec3 c = texture2D(s, t).rgb;
         float a = smoothstep(0.15, 0.45, distance(c, ${key}));
         gl_FragColor = vec4(max(c - (1.0 - a) * ${key}, 0.0), a); }`
      : 'precision mediump float; varying vec2 t; uniform sampler2D s; void main(){ gl_FragColor = texture2D(s, t); }';
    const compile = (type, source) => { const sh = gl.createShader(type); gl.shaderSource(sh, source); gl.compileShader(sh); return sh; };
    const program = gl.createProgram();
    const shaders = [compile(gl.VERTEX_SHADER, vs), compile(gl.FRAGMENT_SHADER, fs)];
    shaders.forEach((sh) => gl.attachShader(program, sh));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS) && !gl.isContextLost()) {
      console.error(`video drawer: ${shaders.map((sh) => gl.getShaderInfoLog(sh)).join(' ')} ${gl.getProgramInfoLog(program)}`);
    }
    const buffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), gl.STATIC_DRAW);
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    const location = gl.getAttribLocation(program, 'p');
    const uniform = gl.getUniformLocation(program, 'u');
    return {
      upload(video) {
        if (video.readyState < 2) return;
        gl.bindTexture(gl.TEXTURE_2D, texture);
        gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, video);
      },
      draw(index, count) {
        gl.useProgram(program);
        gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
        gl.enableVertexAttribArray(location);
        gl.vertexAttribPointer(location, 2, gl.FLOAT, false, 0, 0);
        gl.uniform2f(uniform, index / count, 1 / count);
        gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      },
    };
  }

  // ---------------------------------------------------------------- start
  async function start() {
    const config = await fetchConfig();
    const select = $('scene');
    if (Array.isArray(config.scenes) && config.scenes.length) {
      select.innerHTML = '';
      for (const name of config.scenes) {
        const option = document.createElement('option');
        option.value = option.textContent = name;
        select.appendChild(option);
      }
    }
    $('connect').onclick = () => connect();
    $('disconnect').onclick = () => disconnect();
    $('fullscreen').onclick = () => $('stage').requestFullscreen?.().catch(() => {});
    const size = params.get('size');
    if (size && [...$('size').options].some((o) => o.value === size)) $('size').value = size;
    // `?display=ar`: the key-colour background from the first frame (the choice applies to
    // the next pose; no new session is needed).
    const display = params.get('display');
    if (display && [...$('display').options].some((o) => o.value === display)) $('display').value = display;
    // The quilt is a session of another view count: a new stream; flat and AR share one.
    $('display').onchange = () => {
      const views = $('display').value === 'quilt' ? QUILT.views : 1;
      if (client.wantConnected && !client.xrSession && views !== client.views) {
        disconnect();
        connect();
      }
    };
    $('quilt-info').textContent = `quilt: ${QUILT.views} views, ${QUILT.columns} columns x ${QUILT.rows} rows, ` +
      `view ${QUILT.viewWidth}x${QUILT.viewHeight} (aspect ${(QUILT.viewWidth / QUILT.viewHeight).toFixed(2)}), ` +
      `${QUILT.viewConeDeg} degree view cone, view 0 bottom left`;
    // With the window's size chosen, a new stream once the window has settled at another size.
    let resizeTimer = null;
    window.addEventListener('resize', () => {
      clearTimeout(resizeTimer);
      resizeTimer = setTimeout(() => {
        if ($('size').value !== 'window' || client.xrSession || !client.wantConnected) return;
        const [w, h] = streamSize();
        if (w !== client.width || h !== client.height) {
          disconnect();
          connect();
        }
      }, 500);
    });
    window.addEventListener('pagehide', () => teardown(true));
    installInput();
    setupXr();
    if (params.get('autoconnect') !== '0') connect();
  }

  // Scripted camera moves for tests and demos: orbit angles in radians, radius in metres.
  client.setOrbit = (azimuth, elevation, radius) => {
    client.camera.azimuth = azimuth;
    client.camera.elevation = elevation;
    if (radius) client.camera.radius = radius;
  };

  start();
})();
