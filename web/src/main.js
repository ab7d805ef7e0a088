// The standgrid viewer: a 2-D stand map (OpenLayers) over the service's OGC API and COGs,
// and a 3-D view of a clicked cell's, tree's or payload's points (cell3d.js), with what the robots
// send drawn as it arrives (live.js). Everything it loads comes from the service that serves it
// (no internet), except an optional user-given basemap.
import 'ol/ol.css';
import './style.css';
import Map from 'ol/Map.js';
import View from 'ol/View.js';
import ScaleLine from 'ol/control/ScaleLine.js';
import GeoJSON from 'ol/format/GeoJSON.js';
import TileLayer from 'ol/layer/Tile.js';
import VectorLayer from 'ol/layer/Vector.js';
import WebGLTileLayer from 'ol/layer/WebGLTile.js';
import { register } from 'ol/proj/proj4.js';
import GeoTIFF from 'ol/source/GeoTIFF.js';
import VectorSource from 'ol/source/Vector.js';
import { Circle as CircleStyle, Fill, Stroke, Style, Text } from 'ol/style.js';
import { createEmpty, extend, getCenter, isEmpty } from 'ol/extent.js';
import Point from 'ol/geom/Point.js';
import proj4 from 'proj4';
import { basemapSource } from './basemap.js';
import { openCellView, openPayloadView } from './cell3d.js';
import { startDecoder } from './copcstream.js';
import { startLive } from './live.js';
import { renderStandPage } from './stand.js';
import { RDBU, VIRIDIS, classBreaks, divergingBreaks, formatValue, metricLabel, metricName, metricUnit, rampColours } from './scales.js';

const $ = (id) => document.getElementById(id);
// Columns of stand_metrics that are not metrics to map.
const NOT_METRICS = new Set(['cell_id', 'epoch', 'level', 'cell_size', 'area_m2', 'dominant_by',
  'null_reason']);
const DEFAULT_METRIC = 'zq95';
const NO_DATA = '#c8c8c8';
// The CHM in greys: a backdrop the cells' viridis reads over.
const CHM_RAMP = ['#f4f4f4', '#a9a9a9', '#5e5e5e', '#1e1e1e'];

// A tree's tree_id exactly, as decimal text: from the feature's GeoJSON text.
async function exactTreeId(fid) {
  const url = `/ogc/collections/trees/items/${encodeURIComponent(fid)}`;
  const response = await fetch(url, { headers: { Accept: 'application/geo+json' } });
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  const found = /"tree_id"\s*:\s*(-?\d+)/.exec(await response.text());
  if (!found) throw new Error(`${url}: no tree_id`);
  return found[1];
}

async function getJson(url) {
  const response = await fetch(url, { headers: { Accept: 'application/json' } });
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  return response.json();
}

// Every feature of a collection (all pages), in the catalog CRS when it has an EPSG code.
async function collection(name, crsUri, params = {}) {
  const url = new URL(`/ogc/collections/${name}/items`, window.location.origin);
  url.searchParams.set('limit', '10000');
  if (crsUri) url.searchParams.set('crs', crsUri);
  for (const [key, value] of Object.entries(params)) url.searchParams.set(key, value);
  const features = [];
  let next = url.href;
  while (next) {
    const page = await getJson(next);
    features.push(...page.features);
    next = (page.links || []).find((link) => link.rel === 'next')?.href;
  }
  return { type: 'FeatureCollection', features };
}

const state = {
  config: null, projection: null, epoch: null, metric: DEFAULT_METRIC, breaks: [],
  drawnCells: new Set(), colours: VIRIDIS, cellView: null, treesByEpoch: {},
};

// --- styles -------------------------------------------------------------------------------
function classColour(value) {
  if (value === null || value === undefined || Number.isNaN(value)) return NO_DATA;
  const k = state.breaks.findIndex((upper) => value <= upper);
  return state.colours[k < 0 ? state.colours.length - 1 : k];
}

const styleCache = {};
function fillStyle(colour) {
  if (!styleCache[colour]) {
    styleCache[colour] = new Style({
      fill: new Fill({ color: colour === NO_DATA ? 'rgba(200,200,200,0.6)' : colour }),
      stroke: new Stroke({ color: 'rgba(255,255,255,0.8)', width: 0.6 }),
    });
  }
  return styleCache[colour];
}

function cellStyle(feature) {
  const p = feature.getProperties();
  if (state.change || p.epoch !== state.epoch || p.level !== 0) return null;
  state.drawnCells.add(p.cell_id);
  return fillStyle(classColour(p[state.metric]));
}

// A comparison's 20 m cells: the change of the metric (<metric>_delta of stand_changes).
function changeStyle(feature) {
  const p = feature.getProperties();
  const c = state.change;
  if (!c || p.epoch_from !== c.from || p.epoch_to !== c.to || p.level !== 0) return null;
  state.drawnCells.add(p.cell_id);
  return fillStyle(classColour(p[`${state.metric}_delta`]));
}

const standStyle = new Style({ stroke: new Stroke({ color: '#111', width: 2.2 }) });
const standLabel = (feature, resolution) => {
  const p = feature.getProperties();
  if (p.epoch !== state.epoch || p.level !== 1) return null;
  return [standStyle, new Style({
    text: new Text({
      text: resolution < 1.5 ? `${p.cell_id}` : '', font: '12px system-ui, sans-serif',
      fill: new Fill({ color: '#111' }), stroke: new Stroke({ color: '#fff', width: 3 }),
      placement: 'point', overflow: true, offsetY: -8,
    }),
  })];
};

const byEpoch = (style) => (feature, resolution) => (
  feature.get('epoch') === state.epoch ? (typeof style === 'function' ? style(feature, resolution) : style) : null);

const trajectoryStyle = new Style({ stroke: new Stroke({ color: 'rgba(228,87,46,0.85)', width: 1.5, lineDash: [6, 4] }) });
const payloadStyle = new Style({
  stroke: new Stroke({ color: '#1f6feb', width: 1 }), fill: new Fill({ color: 'rgba(31,111,235,0.06)' }),
  image: new CircleStyle({ radius: 3, fill: new Fill({ color: '#1f6feb' }) }),
});

// Tree crowns outlined in a height ramp (distinct from the cells' viridis), the stem as a
// dot with its DBH (cm) when zoomed in.
const CROWN_RAMP = ['#fee391', '#fe9929', '#cc4c02', '#662506'];
function crownColour(height) {
  const top = state.chmMax || 30;
  const t = Math.min(1, Math.max(0, (height || 0) / top)) * (CROWN_RAMP.length - 1);
  return CROWN_RAMP[Math.min(CROWN_RAMP.length - 1, Math.round(t))];
}
const stemDot = new CircleStyle({ radius: 2.5, fill: new Fill({ color: '#111' }),
  stroke: new Stroke({ color: '#fff', width: 1 }) });
const topDot = new CircleStyle({ radius: 2.5, fill: new Fill({ color: '#fff' }),
  stroke: new Stroke({ color: '#111', width: 1 }) });
// Where a tree is marked (and picked): its fitted stem, else its top.
function markerOf(feature) {
  const p = feature.getProperties();
  const measured = state.stemsInViewCrs && p.stem_x !== null && p.stem_x !== undefined;
  return { measured, at: measured ? [p.stem_x, p.stem_y] : [p.x, p.y] };
}
function treeStyle(feature, resolution) {
  const p = feature.getProperties();
  const styles = [new Style({ stroke: new Stroke({ color: crownColour(p.height_m), width: 1.6 }) })];
  if (resolution < 0.25) {
    // A measured stem: a black dot at the fitted position; otherwise a white dot at the
    // top, its DBH imputed from height (marked "≈").
    const { measured, at } = markerOf(feature);
    styles.push(new Style({
      geometry: new Point(at), image: measured ? stemDot : topDot,
      text: resolution < 0.08 && p.dbh_m ? new Text({
        text: `${measured ? '' : '≈'}${(p.dbh_m * 100).toFixed(0)}`, font: '11px system-ui, sans-serif',
        offsetY: -10, fill: new Fill({ color: '#000' }), stroke: new Stroke({ color: '#fff', width: 3 }),
      }) : undefined,
    }));
  }
  return styles;
}

// --- legend ---------------------------------------------------------------------------------
function renderLegend(features) {
  if (!state.metric) { // no stand metrics (yet): nothing to colour by
    $('legend').innerHTML = '';
    return;
  }
  const unit = metricUnit(state.metric);
  const c = state.change;
  const column = c ? `${state.metric}_delta` : state.metric;
  const shown = features.filter((f) => f.get('level') === 0 && (c
    ? f.get('epoch_from') === c.from && f.get('epoch_to') === c.to : f.get('epoch') === state.epoch));
  const signed = (v) => `${c && v > 0 ? '+' : ''}${formatValue(v, state.metric)}`;
  const counts = new Array(state.breaks.length).fill(0);
  let missing = 0;
  for (const f of shown) {
    const v = f.get(column);
    if (v === null || v === undefined || Number.isNaN(v)) missing += 1;
    else counts[Math.max(0, state.breaks.findIndex((u) => v <= u))] += 1;
  }
  const rows = state.breaks.map((upper, k) => {
    const lower = k === 0 ? state.lower : state.breaks[k - 1];
    return `<tr><td><span class="swatch" style="background:${state.colours[k]}"></span></td>`
      + `<td>${signed(lower)} – ${signed(upper)}</td>`
      + `<td>${counts[k]}</td></tr>`;
  });
  rows.push(`<tr><td><span class="swatch" style="background:${NO_DATA}"></span></td>`
    + `<td>no value</td><td>${missing}</td></tr>`);
  const title = c ? `change in ${metricName(state.metric)}${unit ? ` (${unit})` : ''}, ${c.from} → ${c.to}`
    : `${metricName(state.metric)}${unit ? ` (${unit})` : ''}, ${state.epoch}`;
  $('legend').innerHTML = `<div class="title">${title}</div>`
    + `${c && shown.length && !shown.some((f) => typeof f.get(column) === 'number') ? '<div>no change column for this metric</div>' : ''}`
    + `<table><tr><td></td><td></td><td title="20 m cells">cells</td></tr>`
    + `${rows.join('')}</table>`;
}

// --- map ------------------------------------------------------------------------------------
async function main() {
  const config = await getJson('/viewer/config.json');
  state.config = config;
  $('catalog-name').textContent = config.catalog;
  let dataProjection = 'EPSG:4326';
  let crsUri = null;
  if (config.crs.code) {
    proj4.defs(config.crs.code, config.crs.wkt);
    register(proj4);
    dataProjection = config.crs.code;
    crsUri = config.crs.uri;
    state.stemsInViewCrs = true; // stem_x, stem_y are in the catalog CRS
  }
  state.projection = dataProjection;
  const query = new URLSearchParams(window.location.search);
  // COPC tiles: a cell's points are streamed from its tile by this page (?points=server: by
  // the server, as for LAS/LAZ tiles).
  state.streamCopc = ['copc', 'mixed'].includes(config.tiles) && query.get('points') !== 'server';
  if (query.get('stand')) {
    const attributesOnly = (name, params) => collection(name, null, params);
    attributesOnly.catalog = config.catalog;
    await renderStandPage({ standId: query.get('stand'), epoch: query.get('epoch'),
      collection: attributesOnly, epochs: config.epochs, layers: config.layers });
    return;
  }
  const format = new GeoJSON({ dataProjection, featureProjection: dataProjection });
  // the layers the catalog has now (a live tiling may add some: refreshed by reload())
  const has = (name) => state.config.layers.includes(name);
  const load = async (name, params) => (
    has(name) ? format.readFeatures(await collection(name, crsUri, params)) : []);

  const [metrics, cells, trajectories, payloads, changes] = await Promise.all([
    load('stand_metrics'), load('cells'), load('trajectories'), load('payloads'),
    config.comparisons.length ? load('stand_changes') : []]);
  const metricSource = new VectorSource({ features: metrics });
  const cellSource = new VectorSource({ features: cells });

  const view = new View({ projection: dataProjection, constrainResolution: false });
  const chmLayer = new WebGLTileLayer({ visible: true, opacity: 0.95 });
  const basemapLayer = new TileLayer({ visible: false });
  const cellLayer = new VectorLayer({ source: metricSource, style: cellStyle, opacity: 0.7 });
  const changeLayer = new VectorLayer({ source: new VectorSource({ features: changes }), style: changeStyle, opacity: 0.7 });
  const tileLayer = new VectorLayer({
    source: cellSource, visible: !has('stand_metrics'),
    style: byEpoch(new Style({ stroke: new Stroke({ color: '#555', width: 1 }) })),
  });
  const standLayer = new VectorLayer({ source: metricSource, style: standLabel, declutter: true });
  const trajectoryLayer = new VectorLayer({ source: new VectorSource({ features: trajectories }), style: byEpoch(trajectoryStyle) });
  const payloadLayer = new VectorLayer({ source: new VectorSource({ features: payloads }), style: byEpoch(payloadStyle), visible: false });
  const treeSource = new VectorSource();
  // Crowns only where they can be told apart (a 1 ha overview would be all crowns).
  const treeLayer = new VectorLayer({ source: treeSource, style: treeStyle, declutter: true, maxResolution: 0.5 });
  const selectedSource = new VectorSource();
  const selectedLayer = new VectorLayer({
    source: selectedSource,
    style: new Style({ stroke: new Stroke({ color: '#ff1f1f', width: 3.5 }) }),
  });
  const map = new Map({
    target: 'map',
    layers: [basemapLayer, chmLayer, cellLayer, changeLayer, tileLayer, standLayer, trajectoryLayer, payloadLayer, treeLayer, selectedLayer],
    view,
    controls: [new ScaleLine({ units: 'metric' })],
  });
  map.getControls().extend([]);

  // What a tiling (or a resync of the live view) changed: the catalog's layers read again,
  // in place (the arrays are the ones the clicks search), and the epochs it now has.
  async function reload(event) {
    const fresh = await getJson('/viewer/config.json');
    Object.assign(config, fresh);
    const [m, c, t, p] = await Promise.all([load('stand_metrics'), load('cells'), load('trajectories'), load('payloads')]);
    for (const [array, features, source] of [[metrics, m, metricSource], [cells, c, cellSource],
      [trajectories, t, trajectoryLayer.getSource()], [payloads, p, payloadLayer.getSource()]]) {
      array.splice(0, array.length, ...features);
      source.clear(true);
      source.addFeatures(features);
    }
    const labels = config.epochs.map((e) => e.label);
    if (!labels.includes(state.epoch) && !state.change) state.epoch = labels.includes(event?.epoch) ? event.epoch : labels[0];
    epochOptions();
    await showEpoch();
    restyle();
    const shown = cells.filter((f) => f.get('epoch') === state.epoch).length;
    $('status').textContent = `${shown} cells in ${state.epoch} · updated live (${event?.mission || 'resync'})`;
  }
  const live = startLive({
    map, projection: dataProjection, inCatalogCrs: Boolean(config.crs.code), follow: !cells.length,
    onTiled: reload, onResync: reload, indicator: $('live'),
  });

  // Layer switches.
  const switches = [
    ['CHM (canopy height)', chmLayer, 'chm'], ['20 m cells: metric', cellLayer, 'cells'],
    ['20 m tile cells (outlines)', tileLayer, 'tiles'], ['1 ha stands (outlines)', standLayer, 'stands'],
    ['trees (zoomed in; crown colour: height; ● stem, ○ top: click for the tree; DBH cm, ≈ imputed)', treeLayer, 'trees'], ['trajectories', trajectoryLayer, 'trajectories'],
    ['payload footprints (click: the payload and its points)', payloadLayer, 'payloads'],
  ];
  for (const [label, layer, key] of switches) {
    const row = document.createElement('label');
    row.innerHTML = `<input type="checkbox" data-layer="${key}" ${layer.getVisible() ? 'checked' : ''}/> ${label}`;
    row.querySelector('input').addEventListener('change', (e) => layer.setVisible(e.target.checked));
    $('layers').append(row);
  }

  const opacity = document.createElement('label');
  opacity.innerHTML = 'cell opacity <input id="cell-opacity" type="range" min="0" max="1" step="0.05" value="0.7"/>';
  opacity.querySelector('input').addEventListener('input', (e) => {
    cellLayer.setOpacity(Number(e.target.value));
    changeLayer.setOpacity(Number(e.target.value));
  });
  $('layers').append(opacity);

  // Metric picker: every numeric column of stand_metrics.
  const sample = metrics.find((f) => f.get('level') === 0);
  const columns = sample ? Object.keys(sample.getProperties()).filter((k) => k !== 'geometry'
    && !NOT_METRICS.has(k) && metrics.some((f) => typeof f.get(k) === 'number')) : [];
  if (!columns.includes(state.metric)) state.metric = columns[0];
  $('metric').innerHTML = columns.map((c) => `<option value="${c}">${metricLabel(c)}</option>`).join('');
  $('metric').value = state.metric;
  function epochOptions() {
    $('epoch').innerHTML = config.epochs.map((e) => `<option value="${e.label}">${e.label}`
      + `${e.date ? ` (${e.date})` : ''}</option>`).join('')
      + config.comparisons.map((c) => `<option value="change:${c.key}">change ${c.from} → ${c.to}</option>`).join('');
    $('epoch').value = state.change ? `change:${state.change.key}` : state.epoch;
  }
  state.epoch = config.epochs[0]?.label;
  epochOptions();
  state.change = null;

  // What a control started (read by idle(), so a test waits for it).
  let pending = Promise.resolve();

  function chmSource(path) {
    return path ? new GeoTIFF({
      sources: [{ url: new URL(`/${path}`, window.location.origin).href }],
      normalize: false, interpolate: false, convertToRGB: false, wrapX: false,
    }) : null;
  }

  function rampLegend(title, ramp, lo, hi) {
    const stops = ramp.map((c, k) => `${c} ${(100 * k) / (ramp.length - 1)}%`).join(',');
    return `<div class="title">${title}</div>`
      + `<div class="ramp" style="background:linear-gradient(to right,${stops})"></div>`
      + `<div class="ticks"><span>${lo.toFixed(0)} m</span><span>${((lo + hi) / 2).toFixed(0)} m</span>`
      + `<span>${hi.toFixed(0)} m</span></div>`;
  }

  function rasterStyle(ramp, lo, hi) {
    return {
      color: ['case', ['==', ['band', 2], 0], [0, 0, 0, 0], ['interpolate', ['linear'], ['band', 1],
        ...ramp.flatMap((colour, k) => [lo + ((hi - lo) * k) / (ramp.length - 1), colour])]],
    };
  }

  async function showEpoch() {
    const epoch = config.epochs.find((e) => e.label === state.epoch);
    const c = state.change;
    const top = epoch?.chm_max || 30;
    state.chmMax = top;
    // Crown outline colours: CROWN_RAMP[k] for heights within top / 6 of k * top / 3.
    const edges = [top / 6, top / 2, (5 * top) / 6];
    $('crown-legend').innerHTML = '<div class="title">tree crowns by height</div>' + CROWN_RAMP.map((colour, k) => (
      `<span class="swatch" style="border:2px solid ${colour};background:none"></span> `
      + `${k === 0 ? `< ${edges[0].toFixed(0)}` : k === 3 ? `> ${edges[2].toFixed(0)}` : `${edges[k - 1].toFixed(0)}–${edges[k].toFixed(0)}`} m`
    )).join(' ');
    if (c) {
      const reach = c.chm_diff_max || 10;
      chmLayer.setSource(chmSource(c.chm_diff));
      chmLayer.setStyle(rasterStyle(RDBU, -reach, reach));
      $('chm-legend').innerHTML = c.chm_diff ? rampLegend(`CHM change ${c.from} → ${c.to}`, RDBU, -reach, reach) : '';
    } else {
      chmLayer.setSource(chmSource(epoch?.chm));
      chmLayer.setStyle(rasterStyle(CHM_RAMP, 0, top));
      $('chm-legend').innerHTML = epoch?.chm ? rampLegend('canopy height (CHM)', CHM_RAMP, 0, top) : '';
    }
    treeSource.clear(true);
    if (has('trees')) {
      // Trees come after the first picture; a later epoch switch wins.
      const label = state.epoch;
      state.treesByEpoch[label] ||= load('trees', { epoch: label });
      const trees = await state.treesByEpoch[label];
      if (state.epoch === label) treeSource.addFeatures(trees);
    }
  }

  function restyle() {
    const c = state.change;
    const values = (c ? changes : metrics).filter((f) => f.get('level') === 0)
      .map((f) => f.get(c ? `${state.metric}_delta` : state.metric));
    const { lower, breaks } = c ? divergingBreaks(values) : classBreaks(values, VIRIDIS.length);
    state.lower = lower;
    state.breaks = breaks;
    state.colours = c ? RDBU : rampColours(breaks.length);
    state.drawnCells = new Set();
    renderLegend(c ? changes : metrics);
    cellLayer.changed();
    changeLayer.changed();
    standLayer.changed();
    tileLayer.changed();
    trajectoryLayer.changed();
    payloadLayer.changed();
  }

  $('epoch').addEventListener('change', (e) => {
    const value = e.target.value;
    state.change = config.comparisons.find((c) => `change:${c.key}` === value) || null;
    state.epoch = state.change ? state.change.to : value;
    pending = (async () => {
      const trees = showEpoch();
      restyle();
      await trees;
      // a tree is of one epoch: its cell is reopened; a payload stays (it names its epoch)
      if (state.cellView?.cellId) await openCell(state.cellView.cellId);
    })();
  });
  $('metric').addEventListener('change', (e) => { state.metric = e.target.value; restyle(); });
  // The basemap: an XYZ template or a WMTS capabilities URL; what goes wrong is said next to
  // the field (the map keeps working without it).
  let basemapRequest = 0;
  $('basemap').addEventListener('change', (e) => {
    const request = ++basemapRequest;
    const note = $('basemap-status');
    note.classList.remove('warning');
    note.textContent = e.target.value.trim() ? 'loading…' : '';
    basemapLayer.setSource(null);
    basemapLayer.setVisible(false);
    pending = basemapSource(e.target.value, state.projection).then((source) => {
      if (request !== basemapRequest) return;
      basemapLayer.setSource(source);
      basemapLayer.setVisible(Boolean(source));
      if (!source) return;
      note.textContent = source.get('description');
      let failed = 0;
      source.on('tileloaderror', () => {
        failed += 1;
        note.classList.add('warning');
        note.textContent = `${source.get('description')}: ${failed} tile(s) failed to load`;
      });
    }).catch((error) => {
      if (request !== basemapRequest) return;
      note.classList.add('warning');
      note.textContent = `basemap: ${error.message}`;
    });
  });

  const firstTrees = showEpoch();
  restyle();
  const extent = createEmpty();
  for (const f of cells.length ? cells : metrics) extend(extent, f.getGeometry().getExtent());
  if (!isEmpty(extent)) view.fit(extent, { padding: [20, 20, 20, 20] });
  else {  // an empty catalog: anywhere, until the live view shows what arrives
    view.setCenter([0, 0]);
    view.setZoom(2);
  }

  // Click a cell: its attributes and its points in 3-D.
  async function openCell(cellId, tree = null) {
    const attributes = metrics.find((f) => f.get('cell_id') === cellId && f.get('epoch') === state.epoch);
    const tile = cells.find((f) => f.get('cell_id') === cellId && f.get('epoch') === state.epoch);
    state.cellView?.dispose();
    selectedSource.clear(true);
    if (attributes || tile) selectedSource.addFeature((attributes || tile).clone());
    if (tree) selectedSource.addFeature(tree.clone());
    const epochs = config.epochs.map((e) => e.label)
      .filter((e) => cells.some((f) => f.get('cell_id') === cellId && f.get('epoch') === e));
    const centre = (attributes || tile) ? getCenter((attributes || tile).getGeometry().getExtent()) : null;
    const stand = centre && metrics.find((f) => f.get('level') === 1 && f.get('epoch') === state.epoch
      && f.getGeometry().intersectsCoordinate(centre));
    const page = (id) => `/?stand=${encodeURIComponent(id)}&epoch=${encodeURIComponent(state.epoch)}`;
    $('panel-links').innerHTML = `stand page: <a href="${page(cellId)}" target="_blank">this cell</a>`
      + (stand ? ` · <a href="${page(stand.get('cell_id'))}" target="_blank" id="stand-link">its 1 ha stand ${stand.get('cell_id')}</a>` : '');
    // Each epoch's COPC tile of the cell, streamed within the cell's bounds (in the catalog
    // CRS; the whole tile when the map is not in it).
    const streams = {};
    for (const e of state.streamCopc ? epochs : []) {
      const t = cells.find((f) => f.get('cell_id') === cellId && f.get('epoch') === e);
      const path = t?.get('tile_path');
      if (!path?.endsWith('.copc.laz')) continue;
      streams[e] = { url: `/files/${path}`, bounds: crsUri ? t.getGeometry().getExtent() : null,
        expected: t.get('point_count'), limit: config.max_view_points };
    }
    // A tree in a streamed cell: its points told by its exact 64-bit id, read from the
    // feature's JSON text (a JS number keeps only 53 bits).
    const id = tree && streams[state.epoch] ? await exactTreeId(tree.getId()) : null;
    state.cellView = await openCellView({
      cellId, epoch: state.epoch, attributes: attributes?.getProperties(), tile: tile?.getProperties(), epochs,
      tree: tree ? { fid: tree.getId(), properties: tree.getProperties(), id } : null, streams,
    });
    return state.cellView;
  }

  // Click a payload footprint: its attributes and its points, as the epoch's tiles hold them.
  async function openPayload(feature) {
    state.cellView?.dispose();
    selectedSource.clear(true);
    selectedSource.addFeature(feature.clone());
    const p = feature.getProperties();
    const stamp = `${p.stamp_sec}_${String(p.stamp_nsec).padStart(9, '0')}`;
    $('panel-links').innerHTML = `the mission's cloud of this payload: <a href="/missions/${encodeURIComponent(p.mission)}`
      + `/payloads/${stamp}/cloud.laz" download>LAZ</a> (from the mission folder, when the server has it)`;
    state.cellView = await openPayloadView({ properties: p });
    return state.cellView;
  }
  // The payload under a pixel: of the footprints there, the one whose pose is nearest.
  function payloadAt(pixel) {
    if (!payloadLayer.getVisible()) return null;
    const [cx, cy] = map.getCoordinateFromPixel(pixel);
    let best = null;
    let nearest = Infinity;
    map.forEachFeatureAtPixel(pixel, (f) => {
      const d2 = (f.get('x') - cx) ** 2 + (f.get('y') - cy) ** 2;
      if (d2 < nearest) { nearest = d2; best = f; }
    }, { layerFilter: (layer) => layer === payloadLayer, hitTolerance: 0 });
    return best;
  }
  map.on('singleclick', (event) => {
    // A tree when the click is on its marker (within 8 px; markers are drawn when zoomed
    // in), else the cell under the click.
    let tree = null;
    if (treeLayer.getVisible() && view.getResolution() < 0.25) {
      let nearest = 8 * 8;
      for (const f of treeSource.getFeatures()) {
        const [px, py] = map.getPixelFromCoordinate(markerOf(f).at);
        const d2 = (px - event.pixel[0]) ** 2 + (py - event.pixel[1]) ** 2;
        if (d2 < nearest) { nearest = d2; tree = f; }
      }
    }
    if (tree) {
      pending = openCell(tree.get('cell_id'), tree);
      return;
    }
    const payload = payloadAt(event.pixel);
    if (payload) {
      pending = openPayload(payload);
      return;
    }
    const hit = map.forEachFeatureAtPixel(event.pixel, (f) => f, {
      layerFilter: (layer) => layer === cellLayer || layer === changeLayer || layer === tileLayer,
      hitTolerance: 0,
    });
    if (hit) pending = openCell(hit.get('cell_id'));
  });
  $('panel-close').addEventListener('click', () => { $('panel').hidden = true; $('panel').classList.remove('wide'); selectedSource.clear(); state.cellView?.dispose(); state.cellView = null; map.updateSize(); });

  // Test and automation hook (read by tests/test_viewer_browser.py).
  const idle = async () => {
    await pending;
    await live.pending;
    await new Promise((resolve) => { map.once('rendercomplete', () => resolve()); map.render(); });
  };
  await idle(); // the first map: cells, stands, CHM (performance.now() counts from navigation)
  const navigationMs = performance.now();
  pending = firstTrees;
  await firstTrees;
  const treesMs = performance.now();
  // COPC tiles: the LAZ decoder ready before the first click.
  if (state.streamCopc) await startDecoder();
  $('status').textContent = `${metrics.filter((f) => f.get('level') === 0 && f.get('epoch') === state.epoch).length} cells · `
    + `map in ${(navigationMs / 1000).toFixed(2)} s, trees in ${(treesMs / 1000).toFixed(2)} s`;
  window.standgrid = {
    state, map, idle, live,
    // What the live view drew: the ids (mission/stamp) of the payloads placed on the map, and
    // the map coordinates of a payload's position and of its footprint's ring.
    livePayloads: () => live.payloads.map((p) => `${p.mission}/${p.payload}`),
    liveGeometry: (id) => {
      const f = live.source.getFeatureById(id);
      return f ? f.getGeometry().getCoordinates() : null;
    },
    livePixel: (id) => {
      const f = live.source.getFeatureById(`${id}#position`);
      return f ? map.getPixelFromCoordinate(f.getGeometry().getCoordinates()) : null;
    },
    cellIds: (epoch) => cells.filter((f) => f.get('epoch') === epoch).map((f) => f.get('cell_id')),
    firstMapMs: navigationMs,
    treesMs,
    loadedCells: (epoch) => metrics.filter((f) => f.get('level') === 0 && f.get('epoch') === epoch).length,
    drawnCells: () => state.drawnCells.size,
    cellFill: (cellId) => {
      const c = state.change;
      const f = c ? changes.find((g) => g.get('cell_id') === cellId && g.get('level') === 0
          && g.get('epoch_from') === c.from && g.get('epoch_to') === c.to)
        : metrics.find((g) => g.get('cell_id') === cellId && g.get('epoch') === state.epoch);
      return f ? classColour(f.get(c ? `${state.metric}_delta` : state.metric)) : null;
    },
    pixelOf: (cellId) => {
      const f = metrics.find((g) => g.get('cell_id') === cellId && g.get('epoch') === state.epoch);
      const [x0, y0, x1, y1] = f.getGeometry().getExtent();
      return map.getPixelFromCoordinate([(x0 + x1) / 2, (y0 + y1) / 2]);
    },
    openCell,
    openPayload: (id) => openPayload(payloadLayer.getSource().getFeatures().find((f) => f.get('payload_id') === id)),
    // The pixel of a payload's pose (inside its footprint), given its payload_id.
    payloadPixel: (id) => {
      const f = payloadLayer.getSource().getFeatures().find((g) => g.get('payload_id') === id);
      return f ? map.getPixelFromCoordinate([f.get('x'), f.get('y')]) : null;
    },
    // The pixel of a tree's marker (stem or top), given its feature id (the trees layer's fid).
    treePixel: (fid) => {
      const f = treeSource.getFeatureById(fid);
      return f ? map.getPixelFromCoordinate(markerOf(f).at) : null;
    },
    // The CHM value the map holds at a coordinate (band 1 of the COG as loaded), or null.
    chmAt: (x, y) => {
      const data = chmLayer.getData(map.getPixelFromCoordinate([x, y]));
      return data && data[data.length - 1] !== 0 ? Number(data[0]) : null;
    },
  };
  document.body.dataset.ready = 'true';
}

main().catch((error) => {
  $('status').textContent = `error: ${error.message}`;
  console.error(error);
});
