// The side panel of a clicked cell, tree or payload: its attributes and its points in 3-D
// (three.js). A cell whose tile is COPC is streamed by the browser from the tile itself
// (copcstream.js: range requests, only the octree nodes the cell needs); otherwise, and for a
// tree or a payload, the points are read from /viewer/points/{epoch}/{cell} or
// /viewer/points?payload=<id> (standgrid/serve/viewer.py: encode_points). A cell's epochs are
// shown overlaid in one view or side by side in synchronised views (one camera for all).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { streamCell } from './copcstream.js';
import { VIRIDIS, formatValue, metricLabel } from './scales.js';

const $ = (id) => document.getElementById(id);
const SHOWN = ['observed_fraction', 'n_points', 'zmax', 'zq95', 'zmean', 'pzabove2', 'n_trees',
  'stems_ha', 'basal_area_m2_ha', 'qmd_cm', 'mean_height_m', 'dominant_height_m', 'null_reason'];
const CLASS_COLOURS = { 2: '#a0522d', 1: '#4f9d4f' };
// Epochs overlaid: the clicked epoch, then the others.
const EPOCH_COLOURS = ['#4ea1ff', '#ffb000', '#ff5cc8', '#7ee081'];
const fmt = (n) => n.toLocaleString('en');

// The binary answer: uint32 header length, JSON header, then the arrays it names.
export function decodePoints(buffer) {
  const headerLength = new DataView(buffer).getUint32(0, true);
  const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, headerLength)));
  const n = header.count;
  const sizes = { '<f4': 4, '<u4': 4, u1: 1 };
  const views = { '<f4': Float32Array, '<u4': Uint32Array, u1: Uint8Array };
  let offset = 4 + headerLength;
  const arrays = {};
  for (const [name, dtype] of header.arrays) {
    const width = name === 'xyz' ? 3 : 1;
    // Copy: a typed array needs an offset aligned to its element size.
    arrays[name] = new views[dtype](buffer.slice(offset, offset + n * width * sizes[dtype]));
    offset += n * width * sizes[dtype];
  }
  if (offset !== buffer.byteLength) throw new Error(`points: ${buffer.byteLength} bytes, expected ${offset}`);
  return { header, ...arrays };
}

async function fetchPoints(url, what) {
  const response = await fetch(url);
  if (!response.ok) throw new Error(`points of ${what}: HTTP ${response.status}`);
  return decodePoints(await response.arrayBuffer());
}

const kB = (n) => `${fmt(Math.round(n / 1024))} kB`;

// A cell's points in one epoch: streamed from its COPC tile when ``stream`` names one (see
// streamCell), else the server's answer; ``tree`` ({fid, id}: its exact id as text) has its
// points marked (meta.tree).
function cellPoints(epoch, cellId, stream, tree = null) {
  if (stream) return streamCell({ ...stream, tree });
  return fetchPoints(cellUrl(epoch, cellId, tree ? tree.fid : null), `${cellId} in ${epoch}`);
}

// Where the points came from: a COPC tile streamed by this page (bytes fetched of the
// file's), or the server; a streamed cell whose core points miss the cells layer's count warns.
function showSource(points, expected) {
  const source = $('panel-source');
  const streamed = points.header.meta.copc;
  source.dataset.source = streamed ? 'copc' : 'server';
  source.classList.remove('warning');
  if (!streamed) {
    source.textContent = 'points read by the server (/viewer/points)';
    return;
  }
  const { bytes, file_size: size, requests, nodes_read: nodes, nodes: all } = streamed;
  source.dataset.bytes = String(bytes);
  source.dataset.fileSize = String(size);
  source.dataset.requests = String(requests);
  source.textContent = `streamed from the COPC tile by this page: ${kB(bytes)} fetched of its `
    + `${kB(size)} (${(100 * bytes / size).toFixed(0)} %) in ${requests} range requests, `
    + `${nodes} of its ${all} octree node${all === 1 ? '' : 's'} decoded`;
  if (!points.header.meta.complete) {
    source.classList.add('warning');
    source.textContent += `; the tile holds ${fmt(points.header.meta.total)} core points where the `
      + `cells layer counts ${fmt(expected)}`;
  }
}

const cellUrl = (epoch, cellId, treeFid = null) => `/viewer/points/${encodeURIComponent(epoch)}/`
  + `${encodeURIComponent(cellId)}${treeFid === null ? '' : `?tree=${treeFid}`}`;

// "12,345 points" or, when the server capped the answer, "12,345 points (2,000 shown: every 6.2nd)".
function countText(points, noun = 'points') {
  const { total, capped, stride } = points.header.meta;
  return `${fmt(total)} ${noun}` + (capped ? ` (${fmt(points.header.count)} shown: every `
    + `${stride.toFixed(1)}th, the ${points.header.meta.copc ? "view's" : "server's"} cap)` : '');
}

function ramp(t) {
  const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const k = Math.min(VIRIDIS.length - 2, Math.floor(x));
  const a = new THREE.Color(VIRIDIS[k]);
  return a.lerp(new THREE.Color(VIRIDIS[k + 1]), x - k);
}

function heightTop(points) {
  const height = points.height_above_ground;
  let top = 0;
  for (let i = 0; i < height.length; i += 1) if (height[i] > top) top = height[i];
  return top;
}

// Per-point RGB of ``points`` coloured ``by`` (height ramp from 0 to ``top``).
function colours(points, by, epochIndex, top) {
  const n = points.header.count;
  const out = new Float32Array(n * 3);
  const height = points.height_above_ground;
  const colour = new THREE.Color();
  for (let i = 0; i < n; i += 1) {
    if (by === 'epoch') colour.set(EPOCH_COLOURS[epochIndex % EPOCH_COLOURS.length]);
    else if (by === 'selected') colour.set(points.tree_key[i] === points.header.meta.tree?.key ? '#ff3b3b' : '#56625a');
    else if (by === 'classification') colour.set(CLASS_COLOURS[points.classification[i]] || '#9aa3ad');
    else if (by === 'tree') {
      const key = points.tree_key[i];
      if (key === 0) colour.set('#6b6b6b');
      else colour.setHSL(((key * 2654435761) >>> 0) / 4294967296, 0.75, 0.55);
    } else if (Number.isNaN(height[i])) colour.set('#9aa3ad');
    else colour.copy(ramp(top > 0 ? height[i] / top : 0));
    out.set([colour.r, colour.g, colour.b], i * 3);
  }
  return out;
}

function colourLegend(by, top, clouds) {
  if (by === 'epoch') {
    return clouds.map((c, k) => `<span class="swatch" style="background:${EPOCH_COLOURS[k % EPOCH_COLOURS.length]}"></span> `
      + `${c.epoch}: ${countText(c.points)}`).join('<br/>');
  }
  if (by === 'height') {
    const stops = VIRIDIS.map((c, k) => `${c} ${(100 * k) / (VIRIDIS.length - 1)}%`).join(',');
    return `<div style="height:10px;background:linear-gradient(to right,${stops})"></div>`
      + `<div style="display:flex;justify-content:space-between;font-size:12px"><span>0 m</span>`
      + `<span>${(top / 2).toFixed(1)} m</span><span>${top.toFixed(1)} m</span></div>`
      + (clouds.length > 1 ? '<div style="font-size:12px">one ramp for both views</div>' : '');
  }
  if (by === 'selected') {
    return '<span class="swatch" style="background:#ff3b3b"></span> the selected tree '
      + '<span class="swatch" style="background:#56625a"></span> other points';
  }
  if (by === 'classification') {
    return '<span class="swatch" style="background:#a0522d"></span> ground (2) '
      + '<span class="swatch" style="background:#4f9d4f"></span> other (1)';
  }
  return 'one colour per tree; grey: no tree';
}

// Points of one or more clouds (each at its origin relative to the first's) drawn in one
// view, in overlay, or in one view per cloud side by side; every view shares one camera and
// its controls move all of them.
class PointsView {
  constructor(container, first) {
    this.container = container;
    this.origin = first.header.origin;
    this.material = new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true });
    this.viewports = [];
    this.mode = null;
    this.objects = new Map(); // cloud -> THREE.Points
    const box = new THREE.Box3().setFromBufferAttribute(new THREE.BufferAttribute(first.xyz, 3));
    if (box.isEmpty()) box.set(new THREE.Vector3(), new THREE.Vector3(1, 1, 1));
    const centre = box.getCenter(new THREE.Vector3());
    const size = box.getSize(new THREE.Vector3());
    // z up, looking from the south-east and above.
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.1, 5000);
    this.camera.up.set(0, 0, 1);
    const reach = Math.max(size.x, size.y, size.z, 1) * 1.5;
    this.camera.position.set(centre.x + reach * 0.7, centre.y - reach * 0.9, centre.z + reach * 0.6);
    this.target = centre;
  }

  object(cloud) {
    if (!this.objects.has(cloud)) {
      const g = new THREE.BufferGeometry();
      g.setAttribute('position', new THREE.BufferAttribute(cloud.points.xyz, 3));
      g.setAttribute('color', new THREE.BufferAttribute(new Float32Array(cloud.points.header.count * 3), 3));
      const points = new THREE.Points(g, this.material);
      const shift = cloud.points.header.origin.map((v, i) => v - this.origin[i]);
      points.position.set(shift[0], shift[1], shift[2]);
      this.objects.set(cloud, points);
    }
    return this.objects.get(cloud);
  }

  // Draws ``clouds`` in ``mode`` (single: the first; overlay; side) coloured ``by``.
  show(mode, clouds, by) {
    const shown = mode === 'single' ? clouds.slice(0, 1) : clouds;
    const top = Math.max(0, ...shown.map((c) => heightTop(c.points)));
    for (const [k, cloud] of shown.entries()) {
      const colour = this.object(cloud).geometry.getAttribute('color');
      colour.copyArray(colours(cloud.points, by, k, top));
      colour.needsUpdate = true;
    }
    const groups = mode === 'side' ? shown.map((c) => [c]) : [shown];
    const key = `${mode}:${shown.length}`;
    if (key !== this.mode) this.layout(groups, mode === 'side');
    this.mode = key;
    this.render();
    return top;
  }

  layout(groups, labelled) {
    this.clear();
    const divs = groups.map(() => {
      const div = document.createElement('div');
      div.className = 'viewport';
      this.container.append(div);
      return div;
    });
    const [width, height] = [divs[0].clientWidth, divs[0].clientHeight];
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.viewports = groups.map((clouds, k) => {
      const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
      renderer.setPixelRatio(1);
      renderer.setSize(width, height);
      divs[k].append(renderer.domElement);
      const scene = new THREE.Scene();
      scene.background = new THREE.Color('#1b1f1b');
      for (const cloud of clouds) scene.add(this.object(cloud));
      if (labelled) {
        const label = document.createElement('div');
        label.className = 'viewport-label';
        label.dataset.epoch = clouds[0].epoch;
        label.dataset.count = String(clouds[0].points.header.meta.total);
        label.dataset.shown = String(clouds[0].points.header.count);
        label.textContent = `${clouds[0].epoch} · ${countText(clouds[0].points)}`;
        divs[k].append(label);
      }
      const controls = new OrbitControls(this.camera, renderer.domElement);
      controls.target.copy(this.target);
      controls.update();
      // One camera: a move in any view (pan moves its target) is every view's.
      controls.addEventListener('change', () => {
        this.target.copy(controls.target);
        for (const other of this.viewports) if (other.controls !== controls) other.controls.target.copy(controls.target);
        this.render();
      });
      return { renderer, scene, controls };
    });
  }

  render() {
    for (const { renderer, scene } of this.viewports) renderer.render(scene, this.camera);
  }

  clear() {
    for (const { renderer, scene, controls } of this.viewports) {
      controls.dispose();
      scene.clear();
      renderer.dispose();
      renderer.forceContextLoss(); // the browser keeps only a few WebGL contexts
    }
    this.viewports = [];
    this.container.replaceChildren();
  }

  dispose() {
    this.clear();
    for (const points of this.objects.values()) points.geometry.dispose();
    this.material.dispose();
  }
}

const TREE_ROWS = [['height_m', 'tree height (m)', 1], ['dbh_m', 'DBH (cm)', 100], ['dbh_source', 'DBH source'],
  ['dbh_se_m', 'DBH standard error (cm)', 100], ['crown_area_m2', 'crown area (m²)', 1], ['n_points', 'tree points', 1],
  ['dbh_n_points', 'stem fit points', 1], ['dbh_arc_deg', 'stem fit arc (°)', 1]];
// tree_id is an int64 beyond a double's exact integers: shown from the server's text.

function attributeRows(attributes, tile, tree) {
  const rows = [];
  if (tree) {
    for (const [key, label, scale] of TREE_ROWS) {
      const value = tree[key];
      if (value === null || value === undefined || value === '') continue;
      rows.push([`${label} · ${key}`, typeof value === 'number' && scale ? formatValue(value * scale, key) : value]);
    }
  }
  if (tile) rows.push(['points in the cell (cells layer) · point_count', tile.point_count]);
  if (attributes) {
    for (const key of SHOWN) {
      if (key in attributes && attributes[key] !== null && attributes[key] !== '') {
        const value = attributes[key];
        rows.push([metricLabel(key), typeof value === 'number' ? formatValue(value, key) : value]);
      }
    }
  }
  return rows.map(([k, v]) => `<tr><td>${k}</td><td>${v}</td></tr>`).join('');
}

const PAYLOAD_ROWS = [['payload_id', 'payload id'], ['mission', 'mission'], ['epoch', 'epoch'],
  ['node_id', 'pose graph node'], ['time', 'time (UTC)'], ['stamp', 'stamp (s.ns)'],
  ['point_count', 'points (payloads layer)'], ['x', 'pose x (m)', 3], ['y', 'pose y (m)', 3],
  ['z', 'pose z (m)', 3], ['yaw', 'heading (° anticlockwise from east)', 1]];

function payloadRows(p) {
  const values = { ...p, stamp: `${p.stamp_sec}.${String(p.stamp_nsec).padStart(9, '0')}` };
  return PAYLOAD_ROWS.filter(([key]) => values[key] !== null && values[key] !== undefined && values[key] !== '')
    .map(([key, label, digits]) => {
      const v = values[key];
      const text = digits !== undefined ? v.toFixed(digits) : typeof v === 'number' ? fmt(v) : v;
      return `<tr><td>${label} · ${key}</td><td>${text}</td></tr>`;
    }).join('');
}

function openPanel(title, rows) {
  $('panel').hidden = false;
  $('panel-title').textContent = title;
  $('panel-count').textContent = 'loading points…';
  $('panel-attributes').innerHTML = rows;
  $('panel-count').classList.remove('warning');
  for (const key of ['count', 'shown', 'treeCount', 'payload']) delete $('panel-count').dataset[key];
  $('panel-source').textContent = '';
  $('panel-source').classList.remove('warning');
  for (const key of ['source', 'bytes', 'fileSize', 'requests']) delete $('panel-source').dataset[key];
}

function setLayoutOptions(enabled) {
  const layout = $('view-layout');
  for (const option of layout.options) option.disabled = option.value !== 'single' && !enabled;
  layout.disabled = !enabled;
  if (!enabled) layout.value = 'single';
}

// Opens the panel for one cell (and a tree of it); resolves when its points are drawn.
// ``epochs``: every epoch that has a tile of the cell (overlaid or side by side);
// ``streams``: epoch -> what streamCell needs, for each epoch whose tile is COPC; ``tree``:
// {fid, properties, id} (id: its exact tree_id as text, for a streamed cell).
export async function openCellView({ cellId, epoch, attributes, tile, epochs = [epoch], tree = null, streams = {} }) {
  const t0 = performance.now();
  // The points asked for first: they travel while the panel is laid out.
  const loaded = cellPoints(epoch, cellId, streams[epoch], tree);
  openPanel(tree ? `tree in ${cellId} · ${epoch}` : `${cellId} · ${epoch}`, attributeRows(attributes, tile, tree?.properties));
  const selectedOption = $('colour-by').querySelector('option[value=selected]');
  selectedOption.disabled = !tree;
  if (tree) $('colour-by').value = 'selected';
  else if ($('colour-by').value === 'selected') $('colour-by').value = 'height';
  const others = epochs.filter((e) => e !== epoch);
  setLayoutOptions(others.length > 0);
  window.dispatchEvent(new Event('resize'));

  const points = await loaded;
  const n = points.header.count;
  showSource(points, streams[epoch]?.expected);
  const view = new PointsView($('view3d'), points);
  const buffer = points.header.meta.buffer_points;
  $('panel-count').textContent = `${countText(points)} in the cell`
    + (buffer ? ` (+ ${fmt(buffer)} buffer points in the tile, not shown)` : '');
  $('panel-count').dataset.count = String(points.header.meta.total);
  $('panel-count').dataset.shown = String(n);
  const marked = points.header.meta.tree;
  if (marked) {
    const all = tree?.properties?.n_points;
    $('panel-count').textContent += `; ${fmt(marked.points)} of them of the selected tree`
      + (all && all !== marked.points ? ` (of its ${fmt(all)}: the rest lie in neighbouring cells)` : '');
    $('panel-attributes').insertAdjacentHTML('afterbegin', `<tr><td>tree id · tree_id</td><td>${marked.tree_id}</td></tr>`);
    $('panel-count').dataset.treeCount = String(marked.points);
  }
  // This epoch's points, then the other epochs' (fetched on first use).
  const clouds = [{ epoch, points }];
  let loading = null;
  const loadOthers = () => {
    loading ||= (async () => {
      for (const other of others) {
        const more = await cellPoints(other, cellId, streams[other]);
        clouds.push({ epoch: other, points: more });
        if (more.header.meta.complete === false) {
          $('panel-source').classList.add('warning');
          $('panel-source').textContent += `; ${other}: the tile holds ${fmt(more.header.meta.total)} `
            + `core points where the cells layer counts ${fmt(streams[other].expected)}`;
        }
      }
    })();
    return loading;
  };
  let disposed = false;
  const update = async () => {
    const mode = $('view-layout').value;
    $('colour-by').disabled = mode === 'overlay';
    $('panel').classList.toggle('wide', mode === 'side');
    window.dispatchEvent(new Event('resize'));
    if (mode !== 'single') await loadOthers();
    if (disposed) return;
    const by = mode === 'overlay' ? 'epoch' : $('colour-by').value;
    const top = view.show(mode, clouds, by);
    $('colour-legend').innerHTML = colourLegend(by, top, mode === 'single' ? clouds.slice(0, 1) : clouds);
  };
  $('colour-by').onchange = update;
  $('view-layout').onchange = update;
  await update();
  const ms = performance.now() - t0;
  return {
    cellId, epoch, count: n, ms, treeFid: tree ? tree.fid : null, source: $('panel-source').dataset.source,
    points, // as drawn (read by the tests)
    update,
    dispose() { disposed = true; view.dispose(); },
  };
}

// Opens the panel for one payload (its ``payloads`` row): its attributes and its points as
// the catalog's tiles hold them (georeferenced, enriched); resolves when they are drawn.
export async function openPayloadView({ properties }) {
  const t0 = performance.now();
  const id = properties.payload_id;
  openPanel(`payload ${id} · ${properties.mission}`, payloadRows(properties));
  const selectedOption = $('colour-by').querySelector('option[value=selected]');
  selectedOption.disabled = true;
  if ($('colour-by').value === 'selected') $('colour-by').value = 'height';
  setLayoutOptions(false); // a payload is of one epoch
  $('colour-by').disabled = false;
  $('panel').classList.remove('wide');
  window.dispatchEvent(new Event('resize'));

  const points = await fetchPoints(`/viewer/points?payload=${encodeURIComponent(id)}`, `payload ${id}`);
  const got = points.header.meta.payload;
  showSource(points);
  const view = new PointsView($('view3d'), points);
  $('panel-count').textContent = `${countText(points)} of the payload, from ${got.tiles_with_points} `
    + `tile${got.tiles_with_points === 1 ? '' : 's'} of ${got.epoch}`
    + (got.complete ? '' : `; the tiles hold ${fmt(got.found)} of its ${fmt(got.point_count)} points`);
  $('panel-count').classList.toggle('warning', !got.complete);
  $('panel-count').dataset.count = String(points.header.meta.total);
  $('panel-count').dataset.shown = String(points.header.count);
  $('panel-count').dataset.payload = String(id);
  const clouds = [{ epoch: got.epoch, points }];
  const update = () => {
    const by = $('colour-by').value;
    const top = view.show('single', clouds, by);
    $('colour-legend').innerHTML = colourLegend(by, top, clouds);
  };
  $('colour-by').onchange = update;
  $('view-layout').onchange = null;
  update();
  return {
    payloadId: id, epoch: got.epoch, count: points.header.meta.total, ms: performance.now() - t0,
    update,
    dispose() { view.dispose(); },
  };
}
