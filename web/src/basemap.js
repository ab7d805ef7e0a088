// The optional basemap: an XYZ template ({z}/{x}/{y}) or a WMTS GetCapabilities URL, with
// `#layer=<identifier>` after it to pick a layer other than the first.
import WMTSCapabilities from 'ol/format/WMTSCapabilities.js';
import { equivalent, get as getProjection } from 'ol/proj.js';
import WMTS, { optionsFromCapabilities } from 'ol/source/WMTS.js';
import XYZ from 'ol/source/XYZ.js';

// Whether a URL (without its #fragment) is a WMTS capabilities document.
export const isWmtsCapabilities = (url) => /[?&]request=getcapabilities(&|$)/i.test(url)
  || /WMTSCapabilities\.xml$/i.test(url.split('?')[0]);

// The tile matrix set of a layer to use: one in the map's projection, else EPSG:3857, else
// EPSG:4326 (OpenLayers reprojects the tiles), else any whose CRS OpenLayers knows.
function pickMatrixSet(capabilities, layer, mapProjection) {
  const sets = capabilities.Contents.TileMatrixSet || [];
  const linked = (layer.TileMatrixSetLink || [])
    .map((link) => sets.find((s) => s.Identifier === link.TileMatrixSet))
    .filter((s) => s && getProjection(s.SupportedCRS));
  for (const wanted of [mapProjection, 'EPSG:3857', 'EPSG:4326']) {
    const found = linked.find((s) => equivalent(getProjection(s.SupportedCRS), getProjection(wanted)));
    if (found) return found;
  }
  if (linked.length) return linked[0];
  throw new Error(`layer ${layer.Identifier}: no tile matrix set in a known CRS (has: `
    + `${(layer.TileMatrixSetLink || []).map((l) => l.TileMatrixSet).join(', ') || 'none'})`);
}

async function wmtsSource(url, layerId, mapProjection) {
  let response;
  try {
    response = await fetch(url);
  } catch (error) {
    throw new Error(`${url}: unreachable, or its server does not allow cross-origin requests`
      + ` (${error.message})`);
  }
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  let capabilities;
  try {
    capabilities = new WMTSCapabilities().read(await response.text());
  } catch (error) {
    throw new Error(`${url}: not a WMTS capabilities document (${error.message})`);
  }
  const layers = capabilities?.Contents?.Layer || [];
  if (!layers.length) throw new Error(`${url}: no layer in the capabilities`);
  const layer = layerId ? layers.find((l) => l.Identifier === layerId) : layers[0];
  if (!layer) {
    throw new Error(`${url}: no layer ${layerId} (layers: ${layers.map((l) => l.Identifier).join(', ')})`);
  }
  const matrixSet = pickMatrixSet(capabilities, layer, mapProjection);
  const options = optionsFromCapabilities(capabilities, {
    layer: layer.Identifier, matrixSet: matrixSet.Identifier, crossOrigin: 'anonymous',
  });
  if (!options || !options.urls?.length) throw new Error(`${url}: layer ${layer.Identifier}: no tile URL`);
  const source = new WMTS(options);
  source.set('description', `WMTS layer ${layer.Identifier}, tile matrix set ${matrixSet.Identifier}`);
  return source;
}

// The tile source of what the user typed, or null for an empty field; throws an Error whose
// message says what is wrong.
export async function basemapSource(text, mapProjection) {
  const [url, fragment = ''] = text.trim().split('#', 2);
  if (!url) return null;
  if (isWmtsCapabilities(url)) {
    return wmtsSource(url, new URLSearchParams(fragment).get('layer'), mapProjection);
  }
  if (!/\{z\}/.test(url) || !/\{x\}/.test(url) || !/\{-?y\}/.test(url)) {
    throw new Error('not an XYZ template ({z}, {x} and {y} in it) nor a WMTS capabilities URL'
      + ' (request=GetCapabilities, or …/WMTSCapabilities.xml)');
  }
  const source = new XYZ({ url, crossOrigin: 'anonymous' });
  source.set('description', 'XYZ tiles');
  return source;
}
