// The printable stand page (/?stand=<cell_id>&epoch=<label>): a 1 ha stand's (or a 20 m
// cell's) metrics in every epoch, their change, its tree list and small plots, from /ogc.
import { formatValue, metricName, metricUnit } from './scales.js';

const ROWS = ['observed_fraction', 'n_points', 'zmax', 'zq95', 'zmean', 'pzabove2', 'n_trees',
  'stems_ha', 'basal_area_m2_ha', 'qmd_cm', 'mean_height_m', 'dominant_height_m', 'dbh_measured_share'];
const EPOCH_COLOURS = ['#4e79a7', '#f28e2b', '#59a14f', '#e15759'];

const escapeHtml = (text) => String(text).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' })[c]);

// Bars of several epochs' values per bin, as SVG (no plotting library needed).
function histogram(title, unit, series, step) {
  const all = series.flatMap((s) => s.values);
  if (!all.length) return `<figure><figcaption>${title}: no trees</figcaption></figure>`;
  const lo = Math.floor(Math.min(...all) / step) * step;
  const bins = Math.max(1, Math.ceil((Math.max(...all) - lo) / step + 1e-9));
  const counts = series.map((s) => {
    const c = new Array(bins).fill(0);
    for (const v of s.values) c[Math.min(bins - 1, Math.floor((v - lo) / step))] += 1;
    return c;
  });
  const top = Math.max(...counts.flat(), 1);
  const [w, h, left, bottom] = [320, 150, 28, 28];
  const bw = (w - left - 6) / bins;
  const sub = bw / series.length;
  let bars = '';
  counts.forEach((c, k) => c.forEach((n, i) => {
    const bh = ((h - bottom - 8) * n) / top;
    bars += `<rect x="${left + i * bw + k * sub + 0.5}" y="${h - bottom - bh}" width="${Math.max(1, sub - 1)}" height="${bh}" fill="${EPOCH_COLOURS[k]}"><title>${series[k].label}: ${n}</title></rect>`;
  }));
  let ticks = '';
  const every = Math.ceil(bins / 8);
  for (let i = 0; i <= bins; i += every) {
    ticks += `<text x="${left + i * bw}" y="${h - bottom + 12}" font-size="9" text-anchor="middle">${formatValue(lo + i * step)}</text>`;
  }
  // HTML beside the SVG: each epoch's square in its bars' colour (an SVG <tspan fill>
  // outside an <svg> is an unknown element, its ■ drawn in the text's black)
  const legend = series.map((s, k) => `<span class="swatch" style="background:${EPOCH_COLOURS[k]}"></span> ${escapeHtml(s.label)} (${s.values.length}) `).join('');
  return `<figure><figcaption>${title}</figcaption><svg width="${w}" height="${h}" role="img">`
    + `<line x1="${left}" y1="${h - bottom}" x2="${w - 6}" y2="${h - bottom}" stroke="#333"/>`
    + `<text x="${left - 4}" y="14" font-size="9" text-anchor="end">${top}</text>`
    + `<text x="${left - 4}" y="${h - bottom}" font-size="9" text-anchor="end">0</text>${bars}${ticks}`
    + `<text x="${(w + left) / 2}" y="${h - 3}" font-size="9" text-anchor="middle">${unit}</text></svg>`
    + `<div class="fig-legend">${legend}</div></figure>`;
}

// `layers`: the catalog's collections (the viewer's config lists them): only those are
// asked for, so a catalog without a comparison (no stand_changes) or without trees gives
// no 404 and the page leaves that part out.
export async function renderStandPage({ standId, epoch, collection, epochs, layers }) {
  document.body.classList.add('stand-page');
  document.body.innerHTML = `<article id="stand"><p>loading ${escapeHtml(standId)}…</p></article>`;
  const level1 = standId.startsWith('100m_') || !standId.startsWith('20m_');
  const byStand = level1 ? { stand_id: standId } : { cell_id: standId };
  const none = { features: [] };
  const load = (name, params) => (layers.includes(name) ? collection(name, params) : Promise.resolve(none));
  const [metrics, changes, trees] = await Promise.all([
    load('stand_metrics', { cell_id: standId }),
    load('stand_changes', { cell_id: standId }),
    load('trees', byStand),
  ]);
  const rows = metrics.features.map((f) => f.properties)
    .sort((a, b) => String(a.epoch).localeCompare(String(b.epoch)));
  const labels = rows.map((r) => r.epoch);
  const change = changes.features.map((f) => f.properties)[0];
  const chosen = rows.find((r) => r.epoch === epoch) || rows[0];
  const date = epochs.find((e) => e.label === (chosen && chosen.epoch))?.date;

  const head = `<tr><th>metric</th>${labels.map((l) => `<th>${escapeHtml(l)}</th>`).join('')}`
    + `${change ? `<th>change ${change.epoch_from} → ${change.epoch_to}</th><th>per year</th>` : ''}</tr>`;
  const body = ROWS.filter((k) => rows.some((r) => k in r)).map((k) => {
    const unit = metricUnit(k);
    const cells = rows.map((r) => `<td>${formatValue(r[k], k)}</td>`).join('');
    const delta = change ? `<td>${formatValue(change[`${k}_delta`], `${k}_delta`)}</td><td>${formatValue(change[`${k}_per_year`], `${k}_per_year`)}</td>` : '';
    return `<tr><td>${metricName(k)}${unit ? ` (${unit})` : ''}</td>${cells}${delta}</tr>`;
  }).join('');
  const reasons = rows.filter((r) => r.null_reason).map((r) => `<p class="note">${r.epoch}: ${escapeHtml(r.null_reason)}</p>`).join('');

  const treeRows = trees.features.map((f) => f.properties).filter((t) => !chosen || t.epoch === chosen.epoch)
    .sort((a, b) => b.height_m - a.height_m);
  // one decimal throughout each column (a crown of 7 m² reads "7.0" beside "6.5")
  const treeTable = treeRows.map((t, i) => `<tr><td>${i + 1}</td><td>${formatValue(t.height_m, 'height_m', 1)}</td>`
    + `<td>${t.dbh_m ? formatValue(t.dbh_m * 100, 'dbh_cm', 1) : '–'}</td><td>${escapeHtml(t.dbh_source || '')}</td>`
    + `<td>${formatValue(t.crown_area_m2, 'crown_area_m2', 1)}</td><td>${escapeHtml(t.cell_id)}</td></tr>`).join('');
  const perEpoch = labels.map((label) => ({
    label, trees: trees.features.map((f) => f.properties).filter((t) => t.epoch === label),
  }));
  const plots = histogram('tree heights', 'height (m), 2 m classes',
    perEpoch.map((s) => ({ label: s.label, values: s.trees.map((t) => t.height_m) })), 2)
    + histogram('diameters at breast height', 'DBH (cm), 5 cm classes',
      perEpoch.map((s) => ({ label: s.label, values: s.trees.filter((t) => t.dbh_m).map((t) => t.dbh_m * 100) })), 5);

  document.getElementById('stand').innerHTML = `
    <header><h1>${level1 ? '1 ha stand' : '20 m cell'} ${escapeHtml(standId)}</h1>
      <p>${escapeHtml(collection.catalog)} · epoch ${escapeHtml(chosen ? chosen.epoch : epoch)}${date ? ` (${date})` : ''}
      · <a href="/" class="noprint">back to the map</a> <button class="noprint" onclick="window.print()">print</button></p></header>
    <section><h2>Metrics</h2><table class="metrics">${head}${body}</table>${reasons}</section>
    <section class="plots">${plots}</section>
    <section><h2>Trees (${treeRows.length}, ${escapeHtml(chosen ? chosen.epoch : '')})</h2>
      <table class="trees" id="tree-list"><tr><th>#</th><th>height (m)</th><th>DBH (cm)</th><th>DBH source</th>
      <th>crown (m²)</th><th>cell</th></tr>${treeTable}</table></section>`;
  document.body.dataset.ready = 'true';
  window.standgrid = { standPage: { standId, epoch: chosen ? chosen.epoch : epoch, trees: treeRows.length,
    requested: ['stand_metrics', 'stand_changes', 'trees'].filter((name) => layers.includes(name)) } };
}
