// The side panel of a clicked cell: its attributes and its points in 3-D (three.js), read
// from /viewer/points/{epoch}/{cell} (standgrid/serve/viewer.py: encode_points).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { VIRIDIS, formatValue, metricLabel } from './scales.js';

const $ = (id) => document.getElementById(id);
const SHOWN = ['observed_fraction', 'n_points', 'zmax', 'zq95', 'zmean', 'pzabove2', 'n_trees',
  'stems_ha', 'basal_area_m2_ha', 'qmd_cm', 'mean_height_m', 'dominant_height_m', 'null_reason'];
const CLASS_COLOURS = { 2: '#a0522d', 1: '#4f9d4f' };
// Epochs overlaid: the clicked epoch, then the others.
const EPOCH_COLOURS = ['#4ea1ff', '#ffb000', '#ff5cc8', '#7ee081'];

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

function ramp(t) {
  const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const k = Math.min(VIRIDIS.length - 2, Math.floor(x));
  const a = new THREE.Color(VIRIDIS[k]);
  return a.lerp(new THREE.Color(VIRIDIS[k + 1]), x - k);
}

function colours(points, by, epochIndex = 0) {
  const n = points.header.count;
  const out = new Float32Array(n * 3);
  const height = points.height_above_ground;
  let top = 0;
  for (let i = 0; i < n; i += 1) if (height[i] > top) top = height[i];
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
  return { out, top };
}

function colourLegend(by, top, overlays = []) {
  if (by === 'epoch') {
    return overlays.map((o, k) => `<span class="swatch" style="background:${EPOCH_COLOURS[k % EPOCH_COLOURS.length]}"></span> `
      + `${o.epoch}: ${o.count === null ? 'no tile' : `${o.count.toLocaleString('en')} points`}`).join('<br/>');
  }
  if (by === 'height') {
    const stops = VIRIDIS.map((c, k) => `${c} ${(100 * k) / (VIRIDIS.length - 1)}%`).join(',');
    return `<div style="height:10px;background:linear-gradient(to right,${stops})"></div>`
      + `<div style="display:flex;justify-content:space-between;font-size:12px"><span>0 m</span>`
      + `<span>${(top / 2).toFixed(1)} m</span><span>${top.toFixed(1)} m</span></div>`;
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
      rows.push([`${label} · ${key}`, typeof value === 'number' && scale ? formatValue(value * scale) : value]);
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

async function fetchPoints(epoch, cellId, treeFid = null) {
  const query = treeFid === null ? '' : `?tree=${treeFid}`;
  const response = await fetch(`/viewer/points/${encodeURIComponent(epoch)}/${encodeURIComponent(cellId)}${query}`);
  if (!response.ok) throw new Error(`points of ${cellId} in ${epoch}: HTTP ${response.status}`);
  return decodePoints(await response.arrayBuffer());
}

// Opens the panel for one cell; resolves when its points are drawn. ``epochs``: every epoch
// that has a tile of the cell (for the overlay).
export async function openCellView({ cellId, epoch, attributes, tile, epochs = [epoch], tree = null }) {
  const t0 = performance.now();
  const panel = $('panel');
  panel.hidden = false;
  $('panel-title').textContent = tree ? `tree in ${cellId} · ${epoch}` : `${cellId} · ${epoch}`;
  $('panel-count').textContent = 'loading points…';
  $('panel-attributes').innerHTML = attributeRows(attributes, tile, tree?.properties);
  const selectedOption = $('colour-by').querySelector('option[value=selected]');
  selectedOption.disabled = !tree;
  if (tree) $('colour-by').value = 'selected';
  else if ($('colour-by').value === 'selected') $('colour-by').value = 'height';
  window.dispatchEvent(new Event('resize'));

  const points = await fetchPoints(epoch, cellId, tree ? tree.fid : null);
  const n = points.header.count;

  const container = $('view3d');
  container.replaceChildren();
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(container.clientWidth, container.clientHeight);
  container.append(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color('#1b1f1b');
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(points.xyz, 3));
  const by = $('colour-by').value;
  const { out, top } = colours(points, by);
  geometry.setAttribute('color', new THREE.BufferAttribute(out, 3));
  geometry.computeBoundingBox();
  const box = geometry.boundingBox;
  const centre = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const material = new THREE.PointsMaterial({ size: 2, sizeAttenuation: false, vertexColors: true });
  scene.add(new THREE.Points(geometry, material));

  // z up, looking from the south-east and above.
  const camera = new THREE.PerspectiveCamera(45, container.clientWidth / container.clientHeight, 0.1, 5000);
  camera.up.set(0, 0, 1);
  const reach = Math.max(size.x, size.y, size.z, 1) * 1.5;
  camera.position.set(centre.x + reach * 0.7, centre.y - reach * 0.9, centre.z + reach * 0.6);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.target.copy(centre);
  controls.update();
  const render = () => renderer.render(scene, camera);
  controls.addEventListener('change', render);
  render();

  const buffer = points.header.meta.buffer_points;
  $('panel-count').textContent = `${n.toLocaleString('en')} points in the cell`
    + (buffer ? ` (+ ${buffer.toLocaleString('en')} buffer points in the tile, not shown)` : '');
  $('panel-count').dataset.count = String(n);
  const marked = points.header.meta.tree;
  if (marked) {
    const all = tree?.properties?.n_points;
    $('panel-count').textContent += `; ${marked.points.toLocaleString('en')} of them of the selected tree`
      + (all && all !== marked.points ? ` (of its ${all.toLocaleString('en')}: the rest lie in neighbouring cells)` : '');
    $('panel-attributes').insertAdjacentHTML('afterbegin', `<tr><td>tree id · tree_id</td><td>${marked.tree_id}</td></tr>`);
    $('panel-count').dataset.treeCount = String(marked.points);
  } else delete $('panel-count').dataset.treeCount;
  $('colour-legend').innerHTML = colourLegend(by, top);
  // The other epochs' points of the cell, overlaid (fetched on first use), each at its own
  // origin relative to this epoch's.
  const others = epochs.filter((e) => e !== epoch);
  let overlays = null;
  const overlayGroup = new THREE.Group();
  scene.add(overlayGroup);
  async function loadOverlays() {
    overlays = [{ epoch, count: n }];
    for (const [k, other] of others.entries()) {
      const more = await fetchPoints(other, cellId);
      const g = new THREE.BufferGeometry();
      g.setAttribute('position', new THREE.BufferAttribute(more.xyz, 3));
      g.setAttribute('color', new THREE.BufferAttribute(colours(more, 'epoch', k + 1).out, 3));
      const cloud = new THREE.Points(g, material);
      const shift = more.header.origin.map((v, i) => v - points.header.origin[i]);
      cloud.position.set(shift[0], shift[1], shift[2]);
      overlayGroup.add(cloud);
      overlays.push({ epoch: other, count: more.header.count });
    }
  }
  const recolour = async () => {
    const by = $('colour-by').value;
    if (by === 'epoch' && overlays === null) await loadOverlays();
    overlayGroup.visible = by === 'epoch';
    const next = colours(points, by);
    geometry.getAttribute('color').copyArray(next.out);
    geometry.getAttribute('color').needsUpdate = true;
    $('colour-legend').innerHTML = colourLegend(by, next.top, overlays || []);
    render();
  };
  const epochOption = $('colour-by').querySelector('option[value=epoch]');
  epochOption.disabled = others.length === 0;
  if (epochOption.disabled && $('colour-by').value === 'epoch') $('colour-by').value = 'height';
  if ($('colour-by').value === 'epoch') await recolour();
  $('colour-by').onchange = recolour;
  const ms = performance.now() - t0;
  return {
    cellId, epoch, count: n, ms, treeFid: tree ? tree.fid : null,
    recoloured: () => recolour(),
    dispose() {
      controls.dispose(); geometry.dispose(); material.dispose(); renderer.dispose();
      overlayGroup.children.forEach((c) => c.geometry.dispose());
    },
  };
}
