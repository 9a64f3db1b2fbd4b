// lsqsurfd's job page: the job list at /, one job at /jobs/ID with its result mesh in 3D.
// Everything comes from the server's JSON API (/api/...), which answers as the gRPC API does for
// the same token; the token is kept in this tab's session storage only.
import * as THREE from './three.module.js';
import { OrbitControls } from './OrbitControls.js';
import { DRACOLoader } from './DRACOLoader.js';

const TOKEN_KEY = 'lsqsurf-token';
const POLL_MS = 1000;
const TERMINAL = new Set(['succeeded', 'failed', 'cancelled']);
// A mesh delivered in parts is shown up to this many triangles (a browser's memory, not the job's).
const MAX_PART_TRIANGLES = 20e6;

const $ = (id) => document.getElementById(id);

function stateName(state) {
  return String(state || '').replace(/^JOB_STATE_/, '').toLowerCase();
}

function methodOf(job) {
  const spec = job.spec || {};
  return Object.keys(spec).find((k) => k !== 'preview' && typeof spec[k] === 'object') || '';
}

function time(ms) {
  const n = Number(ms);
  return n ? new Date(n).toLocaleString() : '';
}

function showMessage(text) {
  $('message').textContent = text || '';
}

class ApiError extends Error {
  constructor(status, text) {
    super(text || `HTTP ${status}`);
    this.status = status;
  }
}

async function api(path, as = 'json') {
  const headers = {};
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (token) headers.Authorization = `Bearer ${token}`;
  const response = await fetch(path, { headers, cache: 'no-store' });
  if (!response.ok) {
    let text = await response.text();
    try { text = JSON.parse(text).message || text; } catch { /* plain text */ }
    if (response.status === 401) $('token-form').hidden = false;
    throw new ApiError(response.status, text);
  }
  if (as === 'json') return response.json();
  if (as === 'blob') return response.blob();
  return response.arrayBuffer();
}

function setupTokenForm() {
  $('token-form').addEventListener('submit', (event) => {
    event.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, $('token').value.trim());
    $('token').value = '';
    $('token-form').hidden = true;
    showMessage('');
  });
}

// --- the job list ---------------------------------------------------------------------------

function jobRow(job) {
  const state = stateName(job.state);
  const row = document.createElement('tr');
  row.className = `state-${state}`;
  row.dataset.job = job.id;
  const cells = [
    ['id', null], ['method', methodOf(job)], ['state', state], ['progress', null],
    ['stage', job.stage || ''], ['points', String(job.input_points || '')],
    ['created', time(job.created_ms)], ['updated', time(job.updated_ms)],
  ];
  for (const [name, text] of cells) {
    const cell = row.insertCell();
    cell.className = name;
    if (name === 'id') {
      const link = document.createElement('a');
      link.href = `/jobs/${job.id}`;
      link.textContent = job.id.slice(0, 12);
      link.title = job.id;
      cell.appendChild(link);
    } else if (name === 'progress') {
      const bar = document.createElement('progress');
      bar.max = 1;
      bar.value = Number(job.progress || 0);
      cell.appendChild(bar);
      cell.append(` ${Math.round(100 * Number(job.progress || 0))}%`);
    } else {
      cell.textContent = text;
      if (name === 'points') cell.classList.add('number');
    }
  }
  return row;
}

async function showList() {
  $('list-view').hidden = false;
  const body = $('jobs').tBodies[0];
  for (;;) {
    try {
      const listing = await api('/api/jobs?limit=200');
      body.replaceChildren(...(listing.jobs || []).map(jobRow));
      $('jobs').dataset.updated = String(Date.now());
      const shown = (listing.jobs || []).length;
      showMessage(!shown ? 'No jobs yet.'
        : listing.next_page_token ? `The newest ${shown} jobs; lsqsurf list shows them all.` : '');
    } catch (error) {
      showMessage(`Cannot list the jobs: ${error.message}`);
    }
    await new Promise((resolve) => setTimeout(resolve, POLL_MS));
  }
}

// --- one job --------------------------------------------------------------------------------

function fillTable(table, rows) {
  table.replaceChildren();
  for (const [name, value] of rows) {
    const row = table.insertRow();
    row.insertCell().textContent = name;
    const cell = row.insertCell();
    cell.textContent = value;
    if (typeof value === 'number') cell.classList.add('number');
  }
}

function formatNumber(value) {
  const n = Number(value);
  if (Number.isInteger(n)) return n;
  return Number(n.toPrecision(5));
}

function showFacts(job) {
  const state = stateName(job.state);
  fillTable($('job-facts'), [
    ['method', methodOf(job)], ['state', state], ['stage', job.stage || ''],
    ['progress', `${Math.round(100 * Number(job.progress || 0))}%`], ['error', job.error || ''],
    ['points', Number(job.input_points || 0)], ['created', time(job.created_ms)], ['updated', time(job.updated_ms)],
    ['owner', job.owner || ''], ['results', (job.results || []).join(', ')],
  ]);
  fillTable($('statistics'), (job.statistics || []).map((s) => [s.name, formatNumber(s.value)]));
}

async function showPictures(job) {
  const pictures = $('pictures');
  pictures.replaceChildren();
  for (const name of (job.results || []).filter((r) => r.endsWith('.png'))) {
    const blob = await api(`/api/jobs/${job.id}/results/${encodeURIComponent(name)}`, 'blob');
    const img = document.createElement('img');
    img.alt = name;
    img.title = name;
    img.src = URL.createObjectURL(blob);
    pictures.appendChild(img);
  }
}

// The 3D view: a Draco mesh decoded here by Google's decoder (through three's DRACOLoader).
class Viewer {
  constructor(canvas) {
    this.canvas = canvas;
    // preserveDrawingBuffer: the picture stays readable after it is shown (tests read it).
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.renderer.setClearColor(0xffffff, 1);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(30, 4 / 3, 0.001, 1000);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x5a6070, 1.6));
    const light = new THREE.DirectionalLight(0xffffff, 1.6);
    this.camera.add(light);
    light.position.set(1, 1, 2);
    this.scene.add(this.camera);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.addEventListener('change', () => this.draw());
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.loader = new DRACOLoader();
    this.loader.setDecoderPath('/static/draco/');
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.canvas;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.draw();
  }

  draw() {
    this.renderer.render(this.scene, this.camera);
  }

  decode(buffer, attributeNames) {
    // Unique ids as the server writes them: position 0, normal 1, then the method's scalars.
    const ids = { position: 0, normal: 1 };
    const types = { position: 'Float32Array', normal: 'Float32Array' };
    attributeNames.forEach((name, i) => { ids[`scalar_${name}`] = 2 + i; types[`scalar_${name}`] = 'Float32Array'; });
    return new Promise((resolve, reject) => {
      this.loader.decodeDracoFile(buffer, resolve, ids, types, THREE.LinearSRGBColorSpace, reject);
    });
  }

  async show(buffer, attributeNames) {
    let geometry;
    try {
      geometry = await this.decode(buffer.slice(0), attributeNames);
    } catch (error) {
      console.info(`no scalars as the method names them (${error}); the shape alone`);
      geometry = await this.decode(buffer, []);
      attributeNames = [];
    }
    this.showGeometry(geometry);
    return attributeNames;
  }

  showGeometry(geometry) {
    if (!geometry.getAttribute('normal')) geometry.computeVertexNormals();
    this.geometry = geometry;
    this.material = new THREE.MeshStandardMaterial({ color: 0xb8c4d6, roughness: 0.6, metalness: 0.05,
      side: THREE.DoubleSide, vertexColors: false });
    this.mesh = new THREE.Mesh(geometry, this.material);
    this.scene.add(this.mesh);
    geometry.computeBoundingSphere();
    const { center, radius } = geometry.boundingSphere;
    this.controls.target.copy(center);
    const distance = radius / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2)) * 1.1;
    this.camera.position.copy(center).add(new THREE.Vector3(0.6, 0.45, 0.65).normalize().multiplyScalar(distance));
    this.camera.near = distance / 100;
    this.camera.far = distance * 100;
    this.camera.updateProjectionMatrix();
    this.controls.update();
    this.resize();
  }

  colorBy(name) {
    const scalar = name && this.geometry.getAttribute(`scalar_${name}`);
    if (!scalar) {
      this.material.vertexColors = false;
      this.material.needsUpdate = true;
      this.draw();
      return;
    }
    let lo = Infinity; let hi = -Infinity;
    for (let i = 0; i < scalar.count; i++) { lo = Math.min(lo, scalar.getX(i)); hi = Math.max(hi, scalar.getX(i)); }
    const colors = new Float32Array(scalar.count * 3);
    const color = new THREE.Color();
    for (let i = 0; i < scalar.count; i++) {
      const t = hi > lo ? (scalar.getX(i) - lo) / (hi - lo) : 0.5;
      color.setHSL(0.66 * (1 - t), 0.75, 0.5);
      colors.set([color.r, color.g, color.b], 3 * i);
    }
    this.geometry.setAttribute('color', new THREE.BufferAttribute(colors, 3));
    this.material.color.set(0xffffff);
    this.material.vertexColors = true;
    this.material.needsUpdate = true;
    $('viewer-note').textContent = `${name}: ${formatNumber(lo)} to ${formatNumber(hi)}`;
    this.draw();
  }

  wireframe(on) {
    this.material.wireframe = on;
    this.draw();
  }
}

// One part of a mesh delivered in parts ("LQM1", little-endian; FetchResultRequest in the API):
// first_vertex, the positions, the normals (none or one per vertex), named scalars, and faces in
// the whole mesh's vertex numbers.
function decodeMeshPart(buffer) {
  const view = new DataView(buffer);
  if (new TextDecoder().decode(new Uint8Array(buffer, 0, 4)) !== 'LQM1') throw new Error('not a mesh part (LQM1)');
  let at = 4;
  const count = () => { const v = Number(view.getBigUint64(at, true)); at += 8; return v; };
  const floats = (n) => { const v = new Float32Array(buffer.slice(at, at + 4 * n)); at += 4 * n; return v; };
  at += 8;  // first_vertex: the parts come in order, so their vertices follow on anyway.
  const vertices = count();
  const positions = floats(3 * vertices);
  const normals = floats(3 * count());
  const scalars = {};
  for (let a = count(); a > 0; a--) {
    const length = count();
    const name = new TextDecoder().decode(new Uint8Array(buffer, at, length));
    at += length;
    scalars[name] = floats(count());
  }
  const faceCount = count();
  const faces = new BigInt64Array(buffer.slice(at, at + 24 * faceCount));
  return { positions, normals, scalars, faces };
}

function concatenate(arrays, Type) {
  const out = new Type(arrays.reduce((n, a) => n + a.length, 0));
  let at = 0;
  for (const a of arrays) { out.set(a, at); at += a.length; }
  return out;
}

// A mesh delivered in parts, joined into one geometry; past `maxTriangles` the rest is left out.
async function loadMeshParts(job, names, maxTriangles) {
  const parts = [];
  let triangles = 0;
  for (const name of names) {
    const part = decodeMeshPart(await api(`/api/jobs/${job.id}/results/${name}`, 'buffer'));
    if (triangles + part.faces.length / 3 > maxTriangles && parts.length) break;
    triangles += part.faces.length / 3;
    parts.push(part);
  }
  const vertices = parts.reduce((n, p) => n + p.positions.length / 3, 0);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(concatenate(parts.map((p) => p.positions), Float32Array), 3));
  if (parts.every((p) => p.normals.length === p.positions.length)) {
    geometry.setAttribute('normal', new THREE.BufferAttribute(concatenate(parts.map((p) => p.normals), Float32Array), 3));
  }
  const scalarNames = Object.keys(parts[0].scalars).filter((n) => parts.every((p) => p.scalars[n]));
  for (const n of scalarNames) {
    geometry.setAttribute(`scalar_${n}`, new THREE.BufferAttribute(concatenate(parts.map((p) => p.scalars[n]), Float32Array), 1));
  }
  // Faces may name vertices of earlier parts only; those of parts left out are dropped.
  const index = [];
  for (const part of parts) {
    for (let i = 0; i < part.faces.length; i += 3) {
      const a = Number(part.faces[i]), b = Number(part.faces[i + 1]), c = Number(part.faces[i + 2]);
      if (a < vertices && b < vertices && c < vertices) index.push(a, b, c);
    }
  }
  geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(index), 1));
  return { geometry, scalarNames, shown: parts.length };
}

async function showMesh(job, methods) {
  const viewer = new Viewer($('canvas'));
  const results = job.results || [];
  const parts = results.filter((r) => /^mesh-part-\d+\.lqm$/.test(r)).sort();
  let names;
  if (results.includes('mesh.drc')) {
    const method = methods.find((m) => m.name === methodOf(job));
    const buffer = await api(`/api/jobs/${job.id}/results/mesh.drc`, 'buffer');
    names = await viewer.show(buffer, (method && method.attributes) || []);
  } else if (parts.length) {
    const loaded = await loadMeshParts(job, parts, MAX_PART_TRIANGLES);
    viewer.showGeometry(loaded.geometry);
    names = loaded.scalarNames;
    if (loaded.shown < parts.length) {
      $('viewer-note').textContent = `showing the first ${loaded.shown} of ${parts.length} parts`;
    }
  } else {
    $('viewer-note').textContent = 'This job has no mesh to show.';
    return;
  }
  const select = $('color-by');
  for (const attribute of names) select.add(new Option(attribute, attribute));
  select.addEventListener('change', () => viewer.colorBy(select.value));
  $('wireframe').addEventListener('change', () => viewer.wireframe($('wireframe').checked));
  const canvas = $('canvas');
  canvas.dataset.vertices = String(viewer.geometry.getAttribute('position').count);
  canvas.dataset.triangles = String(viewer.geometry.index ? viewer.geometry.index.count / 3 : 0);
  canvas.dataset.ready = 'mesh';
}

async function showJob(id) {
  $('job-view').hidden = false;
  $('job-id').textContent = id;
  let methods = [];
  try { methods = (await api('/api/methods')).methods || []; } catch { /* colour choices only */ }
  for (;;) {
    let job;
    try {
      job = await api(`/api/jobs/${id}`);
    } catch (error) {
      showMessage(`Cannot show job ${id}: ${error.message}`);
      await new Promise((resolve) => setTimeout(resolve, POLL_MS));
      continue;
    }
    showMessage('');
    showFacts(job);
    const state = stateName(job.state);
    if (TERMINAL.has(state)) {
      if (state === 'succeeded') {
        await showPictures(job).catch((error) => showMessage(`Pictures: ${error.message}`));
        await showMesh(job, methods).catch((error) => {
          $('canvas').dataset.ready = 'error';
          showMessage(`Mesh: ${error.message}`);
        });
      }
      return;
    }
    await new Promise((resolve) => setTimeout(resolve, POLL_MS));
  }
}

setupTokenForm();
const match = window.location.pathname.match(/^\/jobs\/([0-9a-f]+)\/?$/);
if (match) showJob(match[1]); else showList();
