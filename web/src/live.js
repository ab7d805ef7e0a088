// The live view: what the robots send, drawn as it is stored. The page listens to the
// service's event stream (GET /events, Server-Sent Events; docs/SERVICE.md): each payload's
// footprint and position, each mission's growing trajectory, and, once an increment is tiled,
// the new cells (onTiled reloads the catalog's layers). A browser reconnects by itself,
// sending the last event's id: the service replays what it missed, or says "resync".
import Feature from 'ol/Feature.js';
import GeoJSON from 'ol/format/GeoJSON.js';
import VectorLayer from 'ol/layer/Vector.js';
import VectorSource from 'ol/source/Vector.js';
import { createEmpty, extend, isEmpty } from 'ol/extent.js';
import { Circle as CircleStyle, Fill, Stroke, Style } from 'ol/style.js';

const LIVE = '#0a9396';
const TILED = '#6c757d';

function payloadStyle(feature) {
  const colour = feature.get('tiled') ? TILED : LIVE;
  return new Style({
    stroke: new Stroke({ color: colour, width: feature.get('newest') ? 2.5 : 1.5 }),
    fill: new Fill({ color: feature.get('tiled') ? 'rgba(108,117,125,0.06)' : 'rgba(10,147,150,0.15)' }),
    image: new CircleStyle({ radius: 4, fill: new Fill({ color: colour }),
      stroke: new Stroke({ color: '#fff', width: 1 }) }),
  });
}
const trajectoryStyle = new Style({ stroke: new Stroke({ color: LIVE, width: 2.5 }) });

// Start listening. `projection`: the map's; `inCatalogCrs`: the map is in the catalog CRS
// (else WGS 84); `follow`: fit the view to what arrives (the catalog showed nothing yet);
// `onTiled(event)` and `onResync(event)`: reload the catalog's layers (both may be async).
export function startLive({ map, projection, inCatalogCrs, follow, onTiled, onResync, indicator }) {
  const source = new VectorSource();
  const layer = new VectorLayer({ source, style: (f) => (f.get('kind') === 'trajectory' ? trajectoryStyle : payloadStyle(f)), zIndex: 20 });
  map.addLayer(layer);
  const format = new GeoJSON({ dataProjection: projection, featureProjection: projection });
  const geometryOf = (placed) => format.readGeometry(inCatalogCrs ? placed.crs : placed.wgs84);
  const live = {
    layer, source, connected: false, hello: null, events: 0, lastEventId: null, resyncs: 0,
    missions: [], payloads: [], unplaced: [], tiled: [], pending: Promise.resolve(),
  };
  let newest = null;

  function show() {
    const state = live.connected ? 'on' : 'off';
    indicator.className = `live ${state}`;
    const last = live.payloads.at(-1) || live.unplaced.at(-1);
    indicator.innerHTML = `<span class="dot"></span> live${live.connected ? '' : ' (reconnecting…)'}`
      + ` · ${live.payloads.length} payload${live.payloads.length === 1 ? '' : 's'}`
      + `${live.unplaced.length ? ` (+${live.unplaced.length} not placed yet)` : ''}`
      + `${live.tiled.length ? ` · ${live.tiled.length} tiling${live.tiled.length === 1 ? '' : 's'}` : ''}`
      + `${last ? `<br><small>last: ${last.mission} ${last.payload}</small>` : ''}`;
  }

  function fit() {
    if (!follow) return;
    const extent = createEmpty();
    for (const f of source.getFeatures()) extend(extent, f.getGeometry().getExtent());
    if (!isEmpty(extent)) map.getView().fit(extent, { padding: [40, 40, 40, 40], maxZoom: 21 });
  }

  const handlers = {
    mission(data) { live.missions.push(data.mission); },
    payload(data) {
      const id = `${data.mission}/${data.payload}`;
      if (!data.placed) {
        live.unplaced.push(data);
        return;
      }
      live.unplaced = live.unplaced.filter((p) => `${p.mission}/${p.payload}` !== id);
      if (!live.payloads.some((p) => `${p.mission}/${p.payload}` === id)) live.payloads.push(data);
      for (const old of [source.getFeatureById(id), source.getFeatureById(`${id}#position`)]) {
        if (old) source.removeFeature(old);
      }
      const properties = { mission: data.mission, payload: data.payload, points: data.points };
      const made = [
        new Feature({ ...properties, kind: 'payload', geometry: geometryOf(data.footprint) }),
        new Feature({ ...properties, kind: 'position', geometry: geometryOf(data.position) }),
      ];
      made[0].setId(id);
      made[1].setId(`${id}#position`);
      if (newest) newest.forEach((f) => f.set('newest', false));
      newest = made;
      made.forEach((f) => f.set('newest', true));
      source.addFeatures(made);
      fit();
    },
    trajectory(data) {
      const id = `trajectory:${data.mission}`;
      const old = source.getFeatureById(id);
      if (!data.placed || !data.line) {
        if (old) source.removeFeature(old);
        return;
      }
      if (old) {
        old.setGeometry(geometryOf(data.line));
        old.set('nodes', data.nodes);
        return;
      }
      const feature = new Feature({ kind: 'trajectory', mission: data.mission, nodes: data.nodes,
        geometry: geometryOf(data.line) });
      feature.setId(id);
      source.addFeature(feature);
    },
    tiled(data) {
      live.tiled.push(data);
      for (const f of source.getFeatures()) if (f.get('mission') === data.mission) f.set('tiled', true);
      live.pending = live.pending.then(() => onTiled(data));
    },
    resync(data) {
      live.resyncs += 1;
      live.pending = live.pending.then(() => onResync(data));
    },
  };

  const events = new EventSource('/events');
  events.addEventListener('hello', (e) => {
    live.connected = true;
    live.hello = JSON.parse(e.data);
    show();
  });
  for (const [kind, handle] of Object.entries(handlers)) {
    events.addEventListener(kind, (e) => {
      live.events += 1;
      live.lastEventId = e.lastEventId;
      handle(JSON.parse(e.data));
      show();
    });
  }
  events.onerror = () => {
    live.connected = false;
    show();
  };
  live.close = () => events.close();
  show();
  return live;
}
