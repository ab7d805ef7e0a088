// Colour ramps, class breaks and metric names and units (docs/METRICS.md).
export const VIRIDIS = ['#440154', '#414487', '#2a788e', '#22a884', '#7ad151', '#fde725'];
// Change: red loss, blue gain (ColorBrewer RdBu, as the CHM difference's QGIS style).
export const RDBU = ['#b2182b', '#ef8a62', '#fddbc7', '#d1e5f0', '#67a9cf', '#2166ac'];

const NAMES = {
  zmax: 'max height', zmean: 'mean height', zsd: 'height s.d.', zskew: 'height skewness',
  zkurt: 'height kurtosis', zentropy: 'height entropy', pzabovezmean: 'returns above mean height',
  pzabove2: 'canopy cover (returns > 2 m)', n_points: 'returns', n_trees: 'trees',
  stems_ha: 'stems per ha', basal_area_m2_ha: 'basal area', qmd_cm: 'quadratic mean DBH',
  mean_height_m: 'mean tree height', dominant_height_m: 'dominant height',
  density_pts_m2: 'point density', observed_fraction: 'observed share', observed_m2: 'observed area',
  dbh_measured_share: 'DBH measured share', n_dbh_measured: 'DBHs measured',
  n_dbh_imputed: 'DBHs imputed', n_outside_observed: 'returns off observed ground',
  n_no_height: 'returns without height',
};

export function metricUnit(column) {
  if (/^zq\d+$/.test(column) || ['zmax', 'zmean', 'zsd', 'mean_height_m', 'dominant_height_m'].includes(column)) return 'm';
  if (/^pz/.test(column) || /^zpcum/.test(column)) return '%';
  return {
    stems_ha: 'stems/ha', basal_area_m2_ha: 'm²/ha', qmd_cm: 'cm', density_pts_m2: 'pts/m²',
    observed_m2: 'm²',
  }[column] || '';
}

// A metric's name in words (no unit).
export function metricName(column) {
  let name = NAMES[column];
  if (!name && /^zq\d+$/.test(column)) name = `height, ${column.slice(2)}th percentile`;
  if (!name && /^zpcum\d$/.test(column)) name = `returns below ${column.slice(5)}0 % of max height`;
  if (!name && /^pz/.test(column)) {
    name = `returns ${column.slice(2).replace('below', 'below ').replace('to', '–').replace('plus', '+')
      .replace(/p/g, '.')} m`;
  }
  return name || column;
}

// The metric picker's text: name, unit and column.
export function metricLabel(column) {
  const unit = metricUnit(column);
  return `${metricName(column)}${unit ? ` (${unit})` : ''} · ${column}`;
}

function niceStep(span, classes) {
  const raw = span / classes;
  const power = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 2.5, 5, 10].map((m) => m * power).find((s) => s >= raw);
}

// Equal-interval classes on round numbers over the finite values: the lower bound and each
// class's upper bound (the last one >= max).
export function classBreaks(values, classes) {
  const finite = values.filter((v) => typeof v === 'number' && Number.isFinite(v));
  if (!finite.length) return { lower: 0, breaks: [0] };
  const min = Math.min(...finite);
  const max = Math.max(...finite);
  if (max === min) return { lower: min, breaks: [max] };
  let step = niceStep(max - min, classes);
  let lower = Math.floor(min / step) * step;
  while (lower + classes * step < max) {
    step = niceStep(step * 1.01, 1);
    lower = Math.floor(min / step) * step;
  }
  const breaks = [];
  for (let k = 1; k <= classes; k += 1) {
    breaks.push(Number((lower + k * step).toPrecision(12)));
    if (lower + k * step >= max) break;
  }
  return { lower, breaks };
}

// Classes symmetric about 0 for a change (RDBU.length of them, on round numbers): the lower
// bound and each class's upper bound.
export function divergingBreaks(values) {
  const finite = values.filter((v) => typeof v === 'number' && Number.isFinite(v));
  const half = RDBU.length / 2;
  const reach = finite.length ? Math.max(...finite.map(Math.abs)) : 0;
  const step = reach > 0 ? niceStep(reach, half) : 1;
  const breaks = Array.from({ length: RDBU.length }, (_, k) => Number(((k + 1 - half) * step).toPrecision(12)));
  return { lower: -half * step, breaks };
}

// n colours spread over the ramp (its two ends always used).
export function rampColours(n) {
  if (n <= 1) return [VIRIDIS[VIRIDIS.length - 1]];
  return Array.from({ length: n }, (_, k) => VIRIDIS[Math.round((k * (VIRIDIS.length - 1)) / (n - 1))]);
}

// Counts: columns named n_* or *count (n_trees, n_points, dbh_n_points, point_count) and
// their changes (n_trees_delta), not their rates (n_trees_per_year).
export function isCount(column) {
  return typeof column === 'string' && (/(^|_)n_/.test(column) || /(^|_)count(_delta)?$/.test(column))
    && !/_per_/.test(column);
}

// A value for people: '–' for none; counts and other whole numbers as integers with
// thousands separators ("9", "12,345", never "9.00"); other numbers with `digits` decimals
// when given, else by their size (two significant digits below 0.1, at most one decimal
// for a percentage).
export function formatValue(value, column, digits) {
  if (value === null || value === undefined || (typeof value === 'number' && Number.isNaN(value))) return '–';
  if (typeof value !== 'number' || !Number.isFinite(value)) return String(value);
  if (isCount(column)) return Math.round(value).toLocaleString('en');
  let text;
  if (digits !== undefined) text = value.toFixed(digits);
  else if (Number.isInteger(value)) return value.toLocaleString('en');
  else {
    const size = Math.abs(value);
    const percent = column && metricUnit(column) === '%';
    if (size >= 100) text = value.toLocaleString('en', { maximumFractionDigits: 0 });
    else if (size >= 10) text = value.toFixed(1);
    else if (size >= 0.1 || percent) text = value.toFixed(percent ? 1 : 2);
    else text = value.toPrecision(2);
  }
  return /^-[0.,]*$/.test(text) ? text.slice(1) : text; // no "-0.0"
}
