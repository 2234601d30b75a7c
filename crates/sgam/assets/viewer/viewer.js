/* The SGAM world viewer: the page's own code (plain script, no build step). three.js comes from
 * the vendored bundle (window.SGAM_THREE); the run's data from the JSON in #sgam-data, written by
 * `sgam view` / `sgam generate` (crates/sgam/src/view.rs documents every field).
 *
 * Axes: poses are world_from_camera in the run's world (z up for synthetic worlds) with OpenCV
 * camera axes (x right, y down, z forward); the mesh is glTF (y up). data.three_from_world is
 * the one rotation from the first to the second (the one sgam-io writes the GLB with); every
 * pose goes through it here, and nowhere else. */
(function () {
  'use strict';
  const { THREE, OrbitControls, GLTFLoader } = window.SGAM_THREE;
  const data = JSON.parse(document.getElementById('sgam-data').textContent);
  const selftest = /selftest/.test(location.hash);
  const $ = (id) => document.getElementById(id);
  const state = { errors: 0, mesh: null, meshVersion: null, frame: 0, playing: null, tween: null, mode: 'orbit', finished: false };

  function showError(text) {
    $('msg').textContent = String(text);
  }
  window.addEventListener('error', (e) => { state.errors++; showError(e.message); });
  const consoleError = console.error.bind(console);
  console.error = (...args) => { state.errors++; consoleError(...args); };
  window.addEventListener('unhandledrejection', (e) => { state.errors++; showError(e.reason); });

  // ---- axes ---------------------------------------------------------------------------------
  const r = data.three_from_world;
  const threeFromWorld = new THREE.Matrix3().set(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8]);
  const glFromCv = new THREE.Matrix3().set(1, 0, 0, 0, -1, 0, 0, 0, -1);
  const toThree = (v) => new THREE.Vector3(v[0], v[1], v[2]).applyMatrix3(threeFromWorld);
  const up = toThree(data.up_world).normalize();

  /** Pose i in three's axes: position, orientation of a three (OpenGL) camera, and the
   *  rotation three_from_camera_cv (to place frustum corners given in OpenCV camera axes). */
  function pose(i) {
    const p = data.poses[i];
    const worldFromCam = new THREE.Matrix3().set(p[0], p[1], p[2], p[4], p[5], p[6], p[8], p[9], p[10]);
    const threeFromCamCv = threeFromWorld.clone().multiply(worldFromCam);
    const threeFromCamGl = threeFromCamCv.clone().multiply(glFromCv);
    const q = new THREE.Quaternion().setFromRotationMatrix(new THREE.Matrix4().setFromMatrix3(threeFromCamGl));
    return { pos: toThree([p[3], p[7], p[11]]), q, threeFromCamCv };
  }

  // ---- scene --------------------------------------------------------------------------------
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.setSize(window.innerWidth, window.innerHeight);
  document.body.prepend(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xe8eef3);
  const camera = new THREE.PerspectiveCamera(55, window.innerWidth / window.innerHeight, 0.01, 1000);
  camera.up.copy(up); // before the controls: they orbit about camera.up
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = true;
  controls.dampingFactor = 0.12;
  const pathGroup = new THREE.Group();
  scene.add(pathGroup);
  const world = { centre: new THREE.Vector3(), radius: 10, ground: 0, scale: 1 };

  /** Edges of a camera frustum (apex, image corners at depth d) as line-segment endpoints. */
  function frustumPoints(i, d, out) {
    const k = data.intrinsics;
    const { pos, threeFromCamCv } = pose(i);
    const corners = [[0, 0], [k.width, 0], [k.width, k.height], [0, k.height]].map(([u, v]) =>
      new THREE.Vector3(((u - k.cx) / k.fx) * d, ((v - k.cy) / k.fy) * d, d).applyMatrix3(threeFromCamCv).add(pos));
    for (let c = 0; c < 4; c++) {
      out.push(pos, corners[c], corners[c], corners[(c + 1) % 4]);
    }
    // a tick on the image's top edge shows which way is up in the picture
    const top = corners[0].clone().lerp(corners[1], 0.5);
    out.push(top, top.clone().lerp(pos, -0.15));
    return out;
  }
  function lines(points, color, opacity) {
    const g = new THREE.BufferGeometry().setFromPoints(points);
    const o = opacity === undefined ? 1 : opacity;
    return new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color, transparent: o < 1, opacity: o }));
  }
  const current = { frustum: null };

  /** Path, frustums (every data.frustum_every poses), the seed and the current frame. */
  function buildPath() {
    for (const c of [...pathGroup.children]) {
      pathGroup.remove(c);
      c.geometry.dispose();
    }
    current.frustum = null;
    const n = data.poses.length;
    if (n === 0) return;
    const centres = data.poses.map((_, i) => pose(i).pos);
    const steps = centres.slice(1).map((c, i) => c.distanceTo(centres[i])).filter((s) => s > 0).sort((a, b) => a - b);
    const step = steps.length ? steps[steps.length >> 1] : world.radius * 0.05;
    world.scale = Math.max(step * 0.9, world.radius * 0.004);
    const path = new THREE.Line(new THREE.BufferGeometry().setFromPoints(centres), new THREE.LineBasicMaterial({ color: 0xd6336c }));
    pathGroup.add(path);
    const every = Math.max(1, data.frustum_every || 1);
    const pts = [];
    for (let i = every; i < n; i += every) frustumPoints(i, world.scale, pts);
    if (pts.length) pathGroup.add(lines(pts, 0x7048e8, 0.6));
    // the seed: a larger golden frustum and a ball at its centre
    pathGroup.add(lines(frustumPoints(data.seed, world.scale * 1.8, []), 0xf08c00));
    const ball = new THREE.Mesh(new THREE.SphereGeometry(world.scale * 0.25, 16, 12), new THREE.MeshBasicMaterial({ color: 0xf08c00 }));
    ball.position.copy(centres[data.seed]);
    pathGroup.add(ball);
    $('slider').max = String(n - 1);
    if (state.frame < n) setCurrentFrustum(state.frame);
  }

  function setCurrentFrustum(i) {
    if (current.frustum) {
      pathGroup.remove(current.frustum);
      current.frustum.geometry.dispose();
    }
    current.frustum = lines(frustumPoints(i, world.scale * 1.6, []), 0x00a2c7);
    pathGroup.add(current.frustum);
  }

  // ---- frames -------------------------------------------------------------------------------
  function showFrame(i) {
    const thumbs = data.thumbs || {};
    const set = (img, thumb, full) => {
      img.src = thumb || full || '';
      if (thumb && full) {
        const hi = new Image(); // the full-size frame next to the page, when it is there
        hi.onload = () => { if (state.frame === i) img.src = full; };
        hi.src = full;
      }
    };
    set($('frame-rgb'), thumbs.rgb && thumbs.rgb[i], data.frames[i]);
    for (const kind of ['guidance', 'missing']) {
      const list = thumbs[kind];
      $('fig-' + kind).classList.toggle('hidden', !list);
      if (list) set($('frame-' + kind), list[i], null);
    }
    const seed = i === data.seed ? ' · seed' : '';
    $('framelabel').textContent = 'frame ' + i + seed;
    $('frameno').textContent = i + ' / ' + (data.poses.length - 1);
  }

  /** Shows frame i and (unless fly is false) flies the view to pose i over ms milliseconds. */
  function setFrame(i, fly, ms) {
    if (i < 0 || i >= data.poses.length) return;
    state.frame = i;
    $('slider').value = String(i);
    showFrame(i);
    setCurrentFrustum(i);
    if (fly !== false) flyTo(pose(i), ms === undefined ? 700 : ms);
  }

  function flyTo(target, ms) {
    state.tween = { t0: performance.now(), ms: Math.max(ms, 1), p0: camera.position.clone(), q0: camera.quaternion.clone(), p1: target.pos, q1: target.q };
    controls.enabled = false;
  }

  /** How far ahead of the camera the orbit centre goes: where the view ray meets the ground. */
  function lookDistance() {
    const f = new THREE.Vector3();
    camera.getWorldDirection(f);
    const h = camera.position.dot(up) - world.ground;
    const down = -f.dot(up);
    const d = down > 0.05 ? h / down : world.radius * 0.5;
    return Math.min(Math.max(d, world.scale * 2), world.radius * 2);
  }
  function orbitAhead() {
    const f = new THREE.Vector3();
    camera.getWorldDirection(f);
    controls.target.copy(camera.position).addScaledVector(f, lookDistance());
    controls.update();
  }

  // ---- mesh ---------------------------------------------------------------------------------
  function base64Bytes(text) {
    const bin = atob(text.trim());
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out.buffer;
  }

  function meshBuffer(src) {
    if (!src) return Promise.resolve(base64Bytes(document.getElementById('sgam-mesh').textContent));
    if (location.protocol === 'file:') {
      return Promise.reject(new Error(
        'This world\'s mesh (' + (data.mesh.bytes / 1e6).toFixed(0) + ' MB) is not embedded in the page: serve the run folder with\n' +
        '  sgam view RUN --serve\nand open the address it prints.'));
    }
    return fetch(src, { cache: 'no-store' }).then((r) => {
      if (!r.ok) throw new Error(src + ': HTTP ' + r.status);
      return r.arrayBuffer();
    });
  }

  function loadMesh(src, first) {
    return meshBuffer(src).then((buf) => new Promise((resolve, reject) => {
      new GLTFLoader().parse(buf, '', resolve, reject);
    })).then((gltf) => {
      const root = gltf.scene;
      let vertices = 0;
      root.traverse((o) => {
        if (!o.isMesh) return;
        // unlit: the vertex colours are the generated images' colours, shading included
        o.material = new THREE.MeshBasicMaterial({ vertexColors: !!o.geometry.attributes.color, side: THREE.DoubleSide });
        vertices += o.geometry.attributes.position.count;
        state.meshObject = o;
      });
      if (state.mesh) {
        scene.remove(state.mesh);
        state.mesh.traverse((o) => { if (o.isMesh) o.geometry.dispose(); });
      }
      scene.add(root);
      state.mesh = root;
      state.vertices = vertices;
      fitWorld(first);
      return root;
    });
  }

  // ---- tiles: a world written in tiles shows its coarse mesh at once and, served, the cells
  // near the view's centre in full detail (their coarse triangles hidden) --------------------
  function setupTiles() {
    const t = data.tiles;
    if (!t || !state.meshObject) return;
    const obj = state.meshObject;
    obj.geometry.clearGroups();
    for (const c of t.cells) obj.geometry.addGroup(3 * c.first, 3 * c.count, 0);
    obj.material = [obj.material, new THREE.MeshBasicMaterial({ visible: false })];
    const group = new THREE.Group();
    scene.add(group);
    state.tiles = {
      group, next: 0, loaded: 0, failed: 0,
      cells: t.cells.map((c, k) => ({
        k, files: c.files, fine: null, loading: false,
        box: new THREE.Box3(new THREE.Vector3().fromArray(c.min), new THREE.Vector3().fromArray(c.max)),
      })),
    };
  }
  function tileBuffer(file) {
    return fetch(data.tiles.dir + file).then((r) => {
      if (!r.ok) throw new Error(file + ': HTTP ' + r.status);
      return r.arrayBuffer();
    }).then((buf) => new Promise((resolve, reject) => new GLTFLoader().parse(buf, '', resolve, reject)));
  }
  function showCoarse(cell, on) {
    state.meshObject.geometry.groups[cell.k].materialIndex = on ? 0 : 1;
  }
  function loadCell(cell) {
    const ts = state.tiles;
    cell.loading = true;
    Promise.all(cell.files.map(tileBuffer)).then((list) => {
      const g = new THREE.Group();
      for (const gltf of list) {
        gltf.scene.traverse((o) => {
          if (o.isMesh) o.material = new THREE.MeshBasicMaterial({ vertexColors: !!o.geometry.attributes.color, side: THREE.DoubleSide });
        });
        g.add(gltf.scene);
      }
      cell.fine = g;
      ts.group.add(g);
      showCoarse(cell, false);
      ts.loaded++;
      document.body.dataset.sgamFineCells = String(ts.group.children.length);
      console.log('sgam-fine cells=' + ts.group.children.length + ' loaded=' + ts.loaded);
    }, (e) => {
      ts.failed++;
      state.errors++;
      showError('A tile of this world could not be loaded: ' + (e.message || e));
    }).finally(() => { cell.loading = false; });
  }
  function dropCell(cell) {
    state.tiles.group.remove(cell.fine);
    cell.fine.traverse((o) => {
      if (!o.isMesh) return;
      o.geometry.dispose();
      o.material.dispose();
    });
    cell.fine = null;
    showCoarse(cell, true);
    document.body.dataset.sgamFineCells = String(state.tiles.group.children.length);
  }
  /** Twice a second: full detail for the nearest cells within reach of the view's centre. */
  function updateTiles(now) {
    const ts = state.tiles;
    if (!ts || location.protocol === 'file:' || now < ts.next || ts.failed) return;
    ts.next = now + 500;
    const centre = state.mode === 'walk' ? camera.position : controls.target;
    const near = ts.cells
      .map((c) => [c.box.distanceToPoint(centre), c])
      .filter(([d]) => d <= data.tiles.fine_within_m)
      .sort((a, b) => a[0] - b[0])
      .slice(0, data.tiles.max_fine_cells)
      .map(([, c]) => c);
    const wanted = new Set(near);
    for (const c of ts.cells) {
      if (wanted.has(c) && !c.fine && !c.loading) loadCell(c);
      else if (!wanted.has(c) && c.fine) dropCell(c);
    }
  }

  /** World size from the mesh (or the poses), camera planes, and on the first load the view:
   *  from behind the seed and above, the whole world in sight (like overview.png). */
  function fitWorld(first) {
    const box = new THREE.Box3();
    if (state.mesh) box.setFromObject(state.mesh);
    for (let i = 0; i < data.poses.length; i++) box.expandByPoint(pose(i).pos);
    if (box.isEmpty()) return;
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    world.centre.copy(sphere.center);
    world.radius = Math.max(sphere.radius, 1e-3);
    // the ground: the low end of the mesh along up (5th percentile of a sample of vertices)
    const pos = state.meshObject && state.meshObject.geometry.attributes.position;
    if (pos && pos.count) {
      const hs = [];
      const stride = Math.max(1, Math.floor(pos.count / 5000));
      const v = new THREE.Vector3();
      for (let i = 0; i < pos.count; i += stride) hs.push(v.fromBufferAttribute(pos, i).dot(up));
      hs.sort((a, b) => a - b);
      world.ground = hs[Math.floor(hs.length * 0.05)];
    } else {
      world.ground = box.min.dot(up) - world.radius;
    }
    camera.near = world.radius / 2000;
    camera.far = world.radius * 20;
    camera.updateProjectionMatrix();
    buildPath();
    if (!first) return;
    // the seed's heading (its view, or for a camera looking straight down its image's up),
    // seen from 55 degrees above the horizon
    const heading = new THREE.Vector3(0, 1, 0);
    if (data.poses.length) {
      const q = pose(data.seed).q;
      const fwd = new THREE.Vector3(0, 0, -1).applyQuaternion(q).projectOnPlane(up);
      const imageUp = new THREE.Vector3(0, 1, 0).applyQuaternion(q).projectOnPlane(up);
      heading.copy(fwd.lengthSq() > 0.09 ? fwd : imageUp);
    } else {
      heading.projectOnPlane(up);
    }
    if (heading.lengthSq() < 1e-6) heading.set(1, 0, 0).projectOnPlane(up);
    heading.normalize();
    const tilt = THREE.MathUtils.degToRad(55);
    const view = heading.multiplyScalar(Math.cos(tilt)).addScaledVector(up, -Math.sin(tilt));
    const dist = world.radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 0.8;
    camera.position.copy(world.centre).addScaledVector(view, -dist);
    controls.target.copy(world.centre);
    camera.lookAt(world.centre);
    controls.update();
  }

  // ---- navigation: orbit (OrbitControls) and walk (WASD + drag to look) ----------------------
  const keys = new Set();
  function setMode(mode) {
    state.mode = mode;
    controls.enabled = mode === 'orbit' && !state.tween;
    $('mode').textContent = mode === 'orbit' ? 'walk' : 'orbit';
    if (mode === 'orbit') orbitAhead();
  }
  function togglePlay() {
    if (state.playing) {
      clearInterval(state.playing);
      state.playing = null;
    } else if (data.poses.length > 1) {
      if (state.frame >= data.poses.length - 1) setFrame(0, true, 300);
      state.playing = setInterval(() => {
        if (state.frame >= data.poses.length - 1) return togglePlay();
        setFrame(state.frame + 1, true, 140);
      }, 150);
    }
    $('play').textContent = state.playing ? 'pause' : 'play';
  }
  window.addEventListener('keydown', (e) => {
    if (e.code === 'KeyF') setMode(state.mode === 'orbit' ? 'walk' : 'orbit');
    else if (e.code === 'Space') { togglePlay(); e.preventDefault(); }
    else if ((e.code === 'ArrowRight' || e.code === 'ArrowLeft') && e.target !== $('slider')) {
      setFrame(state.frame + (e.code === 'ArrowRight' ? 1 : -1));
      e.preventDefault();
    } else keys.add(e.code);
  });
  window.addEventListener('keyup', (e) => keys.delete(e.code));
  window.addEventListener('blur', () => keys.clear());
  let drag = null;
  renderer.domElement.addEventListener('pointerdown', (e) => { if (state.mode === 'walk') drag = { x: e.clientX, y: e.clientY }; });
  window.addEventListener('pointerup', () => { drag = null; });
  window.addEventListener('pointermove', (e) => {
    if (!drag || state.mode !== 'walk') return;
    const dx = e.clientX - drag.x;
    const dy = e.clientY - drag.y;
    drag = { x: e.clientX, y: e.clientY };
    camera.quaternion.premultiply(new THREE.Quaternion().setFromAxisAngle(up, -dx * 0.004));
    const f = new THREE.Vector3();
    camera.getWorldDirection(f);
    const pitch = Math.asin(Math.max(-1, Math.min(1, f.dot(up))));
    const next = pitch - dy * 0.004;
    if (Math.abs(next) < 1.5) camera.rotateX(-dy * 0.004);
  });
  function walk(dt) {
    const f = new THREE.Vector3();
    camera.getWorldDirection(f);
    const right = new THREE.Vector3().crossVectors(f, up).normalize();
    const v = new THREE.Vector3();
    if (keys.has('KeyW') || keys.has('ArrowUp')) v.add(f);
    if (keys.has('KeyS') || keys.has('ArrowDown')) v.sub(f);
    if (keys.has('KeyD')) v.add(right);
    if (keys.has('KeyA')) v.sub(right);
    if (keys.has('KeyE')) v.add(up);
    if (keys.has('KeyQ')) v.sub(up);
    if (v.lengthSq() === 0) return;
    const speed = world.radius * 0.15 * (keys.has('ShiftLeft') || keys.has('ShiftRight') ? 4 : 1);
    camera.position.addScaledVector(v.normalize(), speed * dt);
  }

  $('slider').addEventListener('input', (e) => setFrame(Number(e.target.value), true, 450));
  $('play').addEventListener('click', togglePlay);
  $('mode').addEventListener('click', () => setMode(state.mode === 'orbit' ? 'walk' : 'orbit'));
  window.addEventListener('resize', () => {
    camera.aspect = window.innerWidth / window.innerHeight;
    camera.updateProjectionMatrix();
    renderer.setSize(window.innerWidth, window.innerHeight);
  });

  let last = performance.now();
  function animate(now) {
    requestAnimationFrame(animate);
    const dt = Math.min((now - last) / 1000, 0.1);
    last = now;
    const tw = state.tween;
    if (tw) {
      const a = Math.min((now - tw.t0) / tw.ms, 1);
      const s = a * a * (3 - 2 * a);
      camera.position.lerpVectors(tw.p0, tw.p1, s);
      camera.quaternion.slerpQuaternions(tw.q0, tw.q1, s);
      if (a >= 1) {
        state.tween = null;
        if (state.mode === 'orbit') {
          controls.enabled = true;
          orbitAhead();
        }
      }
    } else if (state.mode === 'walk') {
      walk(dt);
    } else {
      controls.update();
    }
    updateTiles(now);
    renderer.render(scene, camera);
  }

  // ---- ready flag and self-test ---------------------------------------------------------------
  /** With #selftest in the address: a ray down (along -up) from every camera must meet the mesh
   *  and a ray up must not (poses drawn over the world, not under or beside it). */
  function runSelftest() {
    const rc = new THREE.Raycaster();
    let below = 0;
    let above = 0;
    const down = up.clone().negate();
    for (let i = 0; i < data.poses.length; i++) {
      const p = pose(i).pos;
      rc.set(p, down);
      if (state.mesh && rc.intersectObject(state.mesh, true).length) below++;
      rc.set(p, up);
      if (state.mesh && rc.intersectObject(state.mesh, true).length) above++;
    }
    return 'down=' + below + '/' + data.poses.length + ' up=' + above + '/' + data.poses.length;
  }
  function ready() {
    const b = document.body.dataset;
    if (selftest) b.sgamSelftest = runSelftest();
    b.sgamOpenMs = String(Math.round(performance.now()));
    b.sgamErrors = String(state.errors);
    b.sgamVertices = String(state.vertices || 0);
    b.sgamReady = '1';
    window.__sgamReady = true;
    document.title = document.title.replace(/^(\[ready\] )?/, '[ready] ');
    console.log('sgam-ready open_ms=' + b.sgamOpenMs + ' vertices=' + b.sgamVertices + ' errors=' + b.sgamErrors +
      (selftest ? ' selftest ' + b.sgamSelftest : ''));
  }
  function stats() {
    const m = data.mesh;
    $('stats').textContent = (state.vertices || 0).toLocaleString('en') + ' vertices · ' + (m.triangles || 0).toLocaleString('en') +
      ' triangles (' + ((m.bytes || 0) / 1e6).toFixed(1) + ' MB) · ' + data.poses.length + ' frames' +
      (data.tiles ? ' · coarse world in ' + data.tiles.cells.length + ' cells' +
        (location.protocol === 'file:' ? ' (serve it for full detail: sgam view RUN --serve)' : ', full detail near the view') : '') +
      (data.live ? (state.finished ? ' · run finished' : ' · live') : '');
  }

  // ---- live: poll the generator's state while the world grows -------------------------------
  function poll() {
    fetch(data.live.state, { cache: 'no-store' })
      .then((r) => r.json())
      .then((s) => {
        const grew = s.poses.length !== data.poses.length;
        const follow = state.frame >= data.poses.length - 1;
        data.poses = s.poses;
        data.frames = s.frames;
        if (grew) buildPath();
        let loading = Promise.resolve();
        if (s.mesh && s.mesh.version !== state.meshVersion) {
          const first = state.meshVersion === null;
          state.meshVersion = s.mesh.version;
          data.mesh = s.mesh;
          loading = loadMesh(s.mesh.src, first).then(() => { if (first) ready(); });
        }
        if (grew && follow) setFrame(data.poses.length - 1, false);
        state.finished = !!s.finished;
        if (state.finished) showError('The run finished: its world.html holds the final world.');
        return loading.then(stats);
      })
      .catch(() => {})
      .finally(() => { if (!state.finished) setTimeout(poll, data.live.every_ms); });
  }

  // for scripted checks and the browser's console
  window.__sgamViewer = { camera, controls, state, pose, setFrame, setMode };
  requestAnimationFrame(animate);
  if (data.live) {
    poll();
  } else {
    // #frame=N in the address opens on frame N (the view stays on the whole world)
    const asked = Number((location.hash.match(/frame=(\d+)/) || [])[1]);
    const shown = () => {
      stats();
      if (data.poses.length) setFrame(asked < data.poses.length ? asked : data.seed, false);
    };
    loadMesh(data.mesh.embedded ? null : data.mesh.src, true).then(
      () => {
        setupTiles();
        shown();
        // on screen: two frames rendered after the mesh went into the scene
        requestAnimationFrame(() => requestAnimationFrame(ready));
      },
      (e) => {
        // the path and the frames are still worth a look; the page is not "ready"
        fitWorld(true);
        shown();
        state.errors++;
        showError(e.message || e);
        document.body.dataset.sgamFailed = String(e.message || e);
        console.log('sgam-failed ' + (e.message || e));
      });
  }
})();
