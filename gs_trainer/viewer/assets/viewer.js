// The gaps viewer page: loads the scene (served by `gaps view` as scene.json + the model, or embedded in
// report.html), renders it with GapsSplats, draws the cameras with GapsOverlay, and runs the panel, the
// orbit/fly controls and the URL hash (#camera=test:0&ui=0&mode=fly&frustums=0&orbit=20,-10,1.5).
//
// <html data-state> is "loading", then "ready" once the first frame is drawn (or "error"); with
// data-errors (errors.js) it is what a headless browser's --dump-dom reads.
'use strict';

(() => {
  const M = GapsMath;
  const html = document.documentElement;
  html.dataset.state = 'loading';

  const app = {
    scene: null,
    model: null,
    items: [],  // every camera: {key, label, camera, colour, kind, entry}
    pose: null,  // {R, centre}
    reference: null,  // intrinsics the view is fitted from: {width, height, fx, fy, cx, cy}
    exact: false,  // the canvas takes the reference camera's size exactly (#ui=0 with a camera)
    target: [0, 0, 0],
    up: [0, -1, 0],
    sceneScale: 1,
    frustumDepth: 0.1,
    mode: 'orbit',
    ui: true,
    frustums: true,
    selected: null,
    frames: 0,
  };

  // ---- loading ----

  function embedded(id) {
    const element = document.getElementById(id);
    return element && element.textContent.trim() ? element.textContent : null;
  }

  function base64ToBuffer(text) {
    const binary = atob(text.replace(/\s+/g, ''));
    const bytes = new Uint8Array(binary.length);
    for (let i = 0; i < binary.length; ++i) bytes[i] = binary.charCodeAt(i);
    return bytes.buffer;
  }

  async function fetchChecked(url, kind) {
    const response = await fetch(url);
    if (!response.ok) throw new Error(`GET ${url}: ${response.status} ${response.statusText}`);
    return kind === 'json' ? response.json() : response.arrayBuffer();
  }

  async function loadScene() {
    const sceneText = embedded('gaps-scene');
    if (sceneText) {
      const scene = JSON.parse(sceneText);
      return {scene, buffer: base64ToBuffer(embedded('gaps-model') || '')};
    }
    const scene = await fetchChecked('scene.json', 'json');
    return {scene, buffer: await fetchChecked(scene.model.url, 'buffer')};
  }

  function decodeModel(scene, buffer) {
    const format = scene.model.format;
    if (format === 'packed') return GapsSplats.decodePacked(buffer);
    if (format === 'splat') return GapsSplats.decodeSplat(buffer);
    throw new Error(`unknown model format '${format}'`);
  }

  // ---- cameras ----

  function collectItems(scene) {
    const items = [];
    const counters = {};
    for (const camera of scene.cameras || []) {
      const split = camera.split || 'camera';
      const index = (counters[split] = (counters[split] ?? -1) + 1);
      const colour = GapsOverlay.COLOURS[split] || GapsOverlay.COLOURS.train;
      items.push({key: `${split}:${index}`, label: `${split} ${index}: ${camera.name || ''}`, camera, colour,
                  kind: split});
    }
    for (const phase of scene.phases || []) {
      for (const view of phase.views || []) {
        if (!view.camera) continue;
        const verdict = view.admitted ? 'admitted' : 'rejected';
        items.push({key: `phase:${phase.phase}:${view.id}`, label: `candidate ${view.id}: ${verdict}`,
                    camera: view.camera, colour: GapsOverlay.COLOURS[verdict], kind: 'pseudo', entry: view, phase});
      }
    }
    return items;
  }

  const findItem = (key) => app.items.find((item) => item.key === key) || null;

  // The median camera-space depth of (a sample of) the splats in front of a pose; `fallback` if none.
  function medianDepth(R, centre, fallback) {
    const m = app.model.means, n = app.model.count, step = Math.max(1, Math.floor(n / 20000));
    const t = M.translationOf(R, centre), depths = [];
    for (let i = 0; i < n; i += step) {
      const z = R[6] * m[3 * i] + R[7] * m[3 * i + 1] + R[8] * m[3 * i + 2] + t[2];
      if (z > 0.2) depths.push(z);
    }
    return depths.length ? M.median(depths) : fallback;
  }

  function measureScene() {
    const m = app.model.means, n = app.model.count, step = Math.max(1, Math.floor(n / 20000));
    const axes = [[], [], []];
    for (let i = 0; i < n; i += step) for (let k = 0; k < 3; ++k) axes[k].push(m[3 * i + k]);
    const middle = axes.map(M.median);
    const distances = [];
    for (let i = 0; i < n; i += step) distances.push(M.norm(M.sub([m[3 * i], m[3 * i + 1], m[3 * i + 2]], middle)));
    app.sceneScale = M.median(distances) || 1;
    app.target = middle;
    const cameras = app.items.filter((item) => item.kind !== 'pseudo').map((item) => item.camera);
    app.frustumDepth = 0.1 * app.sceneScale;
    if (cameras.length) {
      app.up = M.normalize(cameras.map((c) => M.scale(M.row(c.R, 1), -1)).reduce(M.add));
      const first = cameras[0];
      app.frustumDepth = 0.1 * medianDepth(first.R, M.centreOf(first.R, first.t), app.sceneScale);
    }
    // Frustums no larger than the spacing of the cameras, so that close ones (a forward-facing capture) stay
    // apart.
    const centres = cameras.map((c) => M.centreOf(c.R, c.t));
    const nearest = centres.map((a, i) => Math.min(...centres.filter((_, j) => j !== i)
                                                             .map((b) => M.norm(M.sub(a, b)))));
    if (centres.length > 1) app.frustumDepth = Math.min(app.frustumDepth, M.median(nearest));
  }

  function defaultReference(width, height) {
    const f = 0.8 * Math.max(width, height);
    return {width, height, fx: f, fy: f, cx: width / 2, cy: height / 2};
  }

  // Looks at the scene from the first training camera, else from outside its middle.
  function homePose() {
    const first = app.items.find((item) => item.kind === 'train') || app.items.find((item) => item.kind !== 'pseudo');
    if (first) return {camera: first.camera, key: first.key};
    const R = M.lookRotation([0, 0, 1], app.up);
    return {pose: {R, centre: M.sub(app.target, M.scale(M.row(R, 2), 3 * app.sceneScale))}};
  }

  // ---- the view ----

  const canvas = document.getElementById('view');
  const gl = canvas.getContext('webgl2', {antialias: false, alpha: false, depth: false, premultipliedAlpha: false,
                                          preserveDrawingBuffer: true});

  function resizeCanvas() {
    const dpr = window.devicePixelRatio || 1;
    if (app.exact) {
      canvas.width = app.reference.width;
      canvas.height = app.reference.height;
      canvas.style.width = `${app.reference.width / dpr}px`;
      canvas.style.height = `${app.reference.height / dpr}px`;
    } else {
      canvas.style.width = '';
      canvas.style.height = '';
      canvas.width = Math.max(1, Math.round(canvas.clientWidth * dpr));
      canvas.height = Math.max(1, Math.round(canvas.clientHeight * dpr));
    }
  }

  // The pinhole view of the canvas: the reference intrinsics scaled to fit it, centred (identity in exact mode).
  function currentView() {
    const W = canvas.width, H = canvas.height, ref = app.reference;
    const s = Math.min(W / ref.width, H / ref.height);
    return {
      R: app.pose.R, t: M.translationOf(app.pose.R, app.pose.centre), centre: app.pose.centre,
      fx: ref.fx * s, fy: ref.fy * s,
      cx: ref.cx * s + (W - ref.width * s) / 2, cy: ref.cy * s + (H - ref.height * s) / 2,
      width: W, height: H,
    };
  }

  let renderer = null, lines = null, framePending = false;

  function renderNow() {
    framePending = false;
    const view = currentView();
    const started = performance.now();
    renderer.render(view, app.scene.background || [0, 0, 0]);
    if (app.ui && app.frustums) lines.draw(view, app.sceneScale);
    app.frames += 1;
    html.dataset.frames = String(app.frames);
    const info = document.getElementById('frame-info');
    if (info) info.textContent = `${view.width}x${view.height}, ${(performance.now() - started).toFixed(0)} ms`;
  }

  function requestRender() {
    if (framePending || !renderer) return;
    framePending = true;
    requestAnimationFrame(renderNow);
  }

  function updateLines() {
    lines.set(app.items.map((item) => ({camera: item.camera,
                                        colour: item.key === app.selected ? GapsOverlay.COLOURS.selected
                                                                          : item.colour})),
              app.frustumDepth);
  }

  // ---- navigation ----

  function jumpTo(item) {
    const c = item.camera;
    app.pose = {R: c.R.slice(), centre: M.centreOf(c.R, c.t)};
    app.reference = {width: c.width, height: c.height, fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy};
    app.target = M.add(app.pose.centre, M.scale(M.row(c.R, 2), medianDepth(c.R, app.pose.centre, app.sceneScale)));
    app.selected = item.key;
    showSelection(item);
    updateLines();
    resizeCanvas();
  }

  function rotateAbout(pivot, rotation) {
    // A world rotation Q about `pivot`: centre' = pivot + Q (centre - pivot), R' = R Q^T.
    app.pose.centre = M.add(pivot, M.mulVec(rotation, M.sub(app.pose.centre, pivot)));
    app.pose.R = M.orthonormalize(M.mul(app.pose.R, M.transpose(rotation)));
  }

  function orbit(dx, dy) {
    rotateAbout(app.target, M.axisAngle(app.up, -0.005 * dx));
    rotateAbout(app.target, M.axisAngle(M.row(app.pose.R, 0), 0.005 * dy));
  }

  function look(dx, dy) {
    rotateAbout(app.pose.centre, M.axisAngle(app.up, -0.003 * dx));
    rotateAbout(app.pose.centre, M.axisAngle(M.row(app.pose.R, 0), 0.003 * dy));
  }

  function pan(dx, dy) {
    const k = M.norm(M.sub(app.target, app.pose.centre)) / Math.max(1, currentView().fy);
    const move = M.add(M.scale(M.row(app.pose.R, 0), -dx * k), M.scale(M.row(app.pose.R, 1), -dy * k));
    app.pose.centre = M.add(app.pose.centre, move);
    app.target = M.add(app.target, move);
  }

  function dolly(amount) {
    if (app.mode === 'orbit') {
      const offset = M.sub(app.pose.centre, app.target);
      app.pose.centre = M.add(app.target, M.scale(offset, Math.exp(amount)));
    } else {
      app.pose.centre = M.add(app.pose.centre, M.scale(M.row(app.pose.R, 2), -amount * app.sceneScale));
    }
  }

  function interacted() {
    app.selected = null;
    updateLines();
    requestRender();
  }

  function installControls() {
    let last = null;
    canvas.addEventListener('contextmenu', (e) => e.preventDefault());
    canvas.addEventListener('pointerdown', (e) => {
      last = {x: e.clientX, y: e.clientY, startX: e.clientX, startY: e.clientY, button: e.button, shift: e.shiftKey};
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!last) return;
      const dpr = window.devicePixelRatio || 1;
      const dx = (e.clientX - last.x) * dpr, dy = (e.clientY - last.y) * dpr;
      last.x = e.clientX;
      last.y = e.clientY;
      if (last.button === 2 || last.button === 1 || last.shift) pan(dx, dy);
      else if (app.mode === 'orbit') orbit(dx, dy);
      else look(dx, dy);
      requestRender();
    });
    canvas.addEventListener('pointerup', (e) => {
      const click = last && Math.hypot(e.clientX - last.startX, e.clientY - last.startY) < 3 && last.button === 0;
      last = null;
      if (click && app.ui && app.frustums) pickAt(e);
    });
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      dolly(0.0015 * e.deltaY);
      requestRender();
    }, {passive: false});
    installKeys();
  }

  function pickAt(e) {
    const rect = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    const pixel = [(e.clientX - rect.left) * dpr, (e.clientY - rect.top) * dpr];
    const item = GapsOverlay.pick(app.items, currentView(), app.frustumDepth, pixel, 12 * dpr);
    if (item) select(item.key);
  }

  function installKeys() {
    const held = new Set();
    const moves = {w: [0, 0, 1], s: [0, 0, -1], a: [-1, 0, 0], d: [1, 0, 0], q: [0, 1, 0], e: [0, -1, 0],
                   arrowup: [0, 0, 1], arrowdown: [0, 0, -1], arrowleft: [-1, 0, 0], arrowright: [1, 0, 0]};
    let lastTime = null;
    const step = (time) => {
      if (held.size === 0) {
        lastTime = null;
        return;
      }
      const dt = lastTime === null ? 1 / 60 : Math.min(0.1, (time - lastTime) / 1000);
      lastTime = time;
      let move = [0, 0, 0];
      for (const key of held) {
        const [x, y, z] = moves[key];
        move = M.add(move, M.add(M.add(M.scale(M.row(app.pose.R, 0), x), M.scale(M.row(app.pose.R, 2), z)),
                                 M.scale(app.up, -y)));
      }
      const delta = M.scale(move, 0.5 * app.sceneScale * dt);
      app.pose.centre = M.add(app.pose.centre, delta);
      app.target = M.add(app.target, delta);
      renderNow();
      requestAnimationFrame(step);
    };
    window.addEventListener('keydown', (e) => {
      if (e.target instanceof HTMLInputElement) return;
      const key = e.key.toLowerCase();
      if (moves[key]) {
        if (held.size === 0) requestAnimationFrame(step);
        held.add(key);
        app.selected = null;
        e.preventDefault();
      } else if (key === 'f') {
        setMode(app.mode === 'orbit' ? 'fly' : 'orbit');
      } else if (key === 'r') {
        goHome();
      } else if (key === 'n' || key === 'p') {
        cycleCamera(key === 'n' ? 1 : -1);
      }
    });
    window.addEventListener('keyup', (e) => held.delete(e.key.toLowerCase()));
    window.addEventListener('blur', () => held.clear());
  }

  function cycleCamera(direction) {
    if (!app.items.length) return;
    const index = app.items.findIndex((item) => item.key === app.selected);
    const next = (index + direction + app.items.length) % app.items.length;
    select(app.items[index < 0 ? 0 : next].key);
  }

  function setMode(mode) {
    app.mode = mode === 'fly' ? 'fly' : 'orbit';
    for (const button of document.querySelectorAll('[data-mode]'))
      button.classList.toggle('active', button.dataset.mode === app.mode);
  }

  function goHome() {
    const home = homePose();
    if (home.camera) {
      select(home.key);
      return;
    }
    app.pose = home.pose;
    app.reference = defaultReference(canvas.width, canvas.height);
    interacted();
  }

  // ---- selection, hash and panel ----

  function select(key) {
    const item = findItem(key);
    if (!item) {
      window.gapsReportError(`no camera '${key}' (cameras: ${app.items.map((i) => i.key).join(', ') || 'none'})`);
      return;
    }
    jumpTo(item);
    setHash({camera: key});
    for (const li of document.querySelectorAll('#cameras li'))
      li.classList.toggle('selected', li.dataset.key === key);
    requestRender();
  }

  function parseHash() {
    const params = {};
    for (const part of location.hash.replace(/^#/, '').split('&')) {
      if (!part) continue;
      const [k, v = ''] = part.split('=');
      params[decodeURIComponent(k)] = decodeURIComponent(v);
    }
    return params;
  }

  function setHash(changes) {
    const params = {...parseHash(), ...changes};
    const text = Object.entries(params).filter(([, v]) => v !== null && v !== undefined)
                     .map(([k, v]) => `${k}=${v}`).join('&');
    try {
      history.replaceState(null, '', `#${text}`);
    } catch (e) {
      // A page without a URL of its own (report.html's iframe) keeps no hash.
    }
  }

  function applyHash() {
    const params = parseHash();
    app.ui = params.ui !== '0';
    app.frustums = params.frustums !== '0';
    document.body.classList.toggle('bare', !app.ui);
    const toggle = document.getElementById('show-frustums');
    if (toggle) toggle.checked = app.frustums;
    if (params.mode) setMode(params.mode);
    const item = params.camera ? findItem(params.camera) : null;
    if (params.camera && !item)
      window.gapsReportError(`#camera=${params.camera}: no such camera (cameras: ${
          app.items.map((i) => i.key).join(', ') || 'none'})`);
    // Without the UI, a camera view is drawn at exactly the camera's size and intrinsics.
    app.exact = !app.ui && item !== null;
    if (item) jumpTo(item);
    resizeCanvas();
    if (params.orbit) applyOrbit(params.orbit);
  }

  // #orbit=YAW,PITCH,ZOOM: degrees about the up axis and the camera's right axis around the orbit target, then
  // the distance to it times e^ZOOM; for links to a view near a camera.
  function applyOrbit(text) {
    const [yaw = 0, pitch = 0, zoom = 0] = text.split(',').map(Number);
    if (![yaw, pitch, zoom].every(Number.isFinite)) {
      window.gapsReportError(`#orbit=${text}: expected YAW,PITCH,ZOOM (numbers)`);
      return;
    }
    rotateAbout(app.target, M.axisAngle(app.up, yaw * Math.PI / 180));
    rotateAbout(app.target, M.axisAngle(M.row(app.pose.R, 0), pitch * Math.PI / 180));
    app.pose.centre = M.add(app.target, M.scale(M.sub(app.pose.centre, app.target), Math.exp(zoom)));
  }

  function element(tag, attributes = {}, text = '') {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attributes)) e.setAttribute(k, v);
    if (text) e.textContent = text;
    return e;
  }

  function showSelection(item) {
    const box = document.getElementById('selection');
    if (!box) return;
    box.replaceChildren();
    const c = item.camera;
    box.append(element('div', {class: 'title'}, item.label));
    box.append(element('div', {}, `${c.width}x${c.height}, fx ${c.fx.toFixed(1)}, fy ${c.fy.toFixed(1)}, ` +
                                      `cx ${c.cx.toFixed(1)}, cy ${c.cy.toFixed(1)}`));
    if (item.entry) {
      const e = item.entry;
      // Reasons of the admission gate start with the decision; others (no gate) get it in front.
      const verdict = e.admitted ? 'admitted' : 'rejected';
      const reason = (e.reason || '').startsWith(verdict) ? e.reason : `${verdict}: ${e.reason || ''}`;
      box.append(element('div', {class: verdict}, `phase ${item.phase.phase}: ${reason}`));
      if (typeof e.coverage === 'number') box.append(element('div', {}, `coverage ${e.coverage.toFixed(2)}`));
      if (e.image) box.append(element('img', {src: e.image, alt: `pseudo-view ${e.id}`}));
    }
  }

  function cameraList(title, items, open) {
    const details = element('details');
    if (open) details.open = true;
    details.append(element('summary', {}, title));
    const list = element('ul');
    for (const item of items) {
      const li = element('li', {'data-key': item.key, title: item.entry ? item.entry.reason || '' : ''});
      const swatch = element('span', {class: 'swatch'});
      swatch.style.background = `rgb(${item.colour.map((v) => Math.round(255 * v)).join(',')})`;
      li.append(swatch, document.createTextNode(item.label));
      if (item.entry && item.entry.reason) li.append(element('div', {class: 'reason'}, item.entry.reason));
      li.addEventListener('click', () => select(item.key));
      list.append(li);
    }
    details.append(list);
    return details;
  }

  function buildPanel() {
    const scene = app.scene, model = app.model;
    document.getElementById('title').textContent = scene.title || 'gaps viewer';
    document.title = scene.title || 'gaps viewer';
    document.getElementById('model-info').textContent =
        `${model.count.toLocaleString('en')} Gaussians, SH degree ${model.degree}, ` +
        `${renderer.targetFormat} blending`;
    const lists = document.getElementById('cameras');
    lists.replaceChildren();
    for (const split of ['train', 'test']) {
      const items = app.items.filter((item) => item.kind === split);
      if (items.length) lists.append(cameraList(`${split === 'train' ? 'Training' : 'Test'} cameras`, items, true));
    }
    for (const phase of scene.phases || []) {
      const items = app.items.filter((item) => item.phase === phase);
      const admitted = (phase.views || []).filter((v) => v.admitted).length;
      const title = `Phase ${phase.phase} (iteration ${phase.iteration}): ${admitted} of ${
          (phase.views || []).length} admitted`;
      if (items.length) lists.append(cameraList(title, items, false));
    }
    for (const note of scene.notes || []) lists.append(element('p', {class: 'note'}, note));
    for (const button of document.querySelectorAll('[data-mode]'))
      button.addEventListener('click', () => setMode(button.dataset.mode));
    document.getElementById('home').addEventListener('click', goHome);
    document.getElementById('show-frustums').addEventListener('change', (e) => {
      app.frustums = e.target.checked;
      setHash({frustums: app.frustums ? null : '0'});
      requestRender();
    });
  }

  // ---- start ----

  async function start() {
    if (!gl) throw new Error('this browser has no WebGL2');
    const {scene, buffer} = await loadScene();
    app.scene = scene;
    app.model = decodeModel(scene, buffer);
    renderer = new GapsSplats.Renderer(gl);
    renderer.setModel(app.model);
    lines = new GapsOverlay.Lines(gl);
    app.items = collectItems(scene);
    measureScene();
    buildPanel();
    resizeCanvas();
    const home = homePose();
    if (home.camera) jumpTo(findItem(home.key));
    else {
      app.pose = home.pose;
      app.reference = defaultReference(canvas.width, canvas.height);
    }
    app.selected = parseHash().camera ? app.selected : null;
    applyHash();
    updateLines();
    installControls();
    window.addEventListener('hashchange', () => {
      applyHash();
      requestRender();
    });
    window.addEventListener('resize', () => {
      resizeCanvas();
      requestRender();
    });
    renderNow();
    const error = gl.getError();
    if (error !== gl.NO_ERROR) throw new Error(`WebGL error 0x${error.toString(16)} while drawing`);
    html.dataset.state = 'ready';
  }

  start().catch((e) => {
    html.dataset.state = 'error';
    window.gapsReportError(e && e.stack ? e.stack : e);
  });
})();
