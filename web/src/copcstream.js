// A cell's points streamed by the browser from its COPC tile (served at /files/<tile> with
// HTTP range requests): the header and VLRs, the octree hierarchy, then only the nodes whose
// bounds meet the cell's, decoded with the `copc` package (LAZ by laz-perf's WebAssembly,
// served from the bundle). The answer has the shape of decodePoints' (cell3d.js), so the
// 3-D view draws it as it draws the server's /viewer/points answer.
import { Bounds, Copc, Hierarchy, Key, Las } from 'copc';
import { createLazPerf } from 'laz-perf';
import lazPerfWasm from 'laz-perf/lib/web/laz-perf.wasm?url';

let lazPerfReady = null;
// One laz-perf instance for the page, its wasm from the bundle (no CDN).
const lazPerf = () => (lazPerfReady ||= createLazPerf({ locateFile: () => lazPerfWasm }));
// Starts laz-perf (fetch and compile its wasm) before the first cell is clicked.
export const startDecoder = () => lazPerf().then(() => undefined);

// What copc.js reads first (its header read-ahead), and the end of the file fetched beside it:
// the EVLRs (the hierarchy's root page) of a tile are there, so the hierarchy costs no round trip.
const HEAD = 65536;
const TAIL = 8192;

// Byte ranges of one file over HTTP: every request must be answered 206 Partial Content;
// bytes already fetched are served again from memory (copc.js re-reads the header area).
class RangeReader {
  constructor(url) {
    this.url = url;
    this.chunks = []; // {begin, data}, as fetched
    this.bytes = 0;
    this.requests = 0;
    this.size = null; // the file's size, from Content-Range
  }

  // The bytes [begin, end), or with ``begin`` null the last ``end`` bytes of the file.
  async fetchRange(begin, end) {
    const range = begin === null ? `bytes=-${end}` : `bytes=${begin}-${end - 1}`;
    const response = await fetch(this.url, { headers: { Range: range } });
    if (response.status !== 206) {
      throw new Error(`${this.url}: HTTP ${response.status} to a range request (206 expected)`);
    }
    const sent = /^bytes (\d+)-(\d+)\/(\d+)$/.exec(response.headers.get('Content-Range') || '');
    if (!sent) throw new Error(`${this.url}: no Content-Range in the answer to ${range}`);
    this.size = Number(sent[3]);
    const data = new Uint8Array(await response.arrayBuffer());
    this.requests += 1;
    this.bytes += data.byteLength;
    this.chunks.push({ begin: Number(sent[1]), data });
    return data;
  }

  // The head and the tail of the file at once (they overlap in a file under HEAD + TAIL).
  async start() {
    await Promise.all([this.fetchRange(0, HEAD), this.fetchRange(null, TAIL)]);
  }

  // The bytes [begin, end) (fewer at the end of the file), as copc.js's Getter: the parts
  // already held copied, only the gaps between them fetched.
  get = async (begin, end) => {
    if (this.size !== null) end = Math.min(end, this.size);
    const out = new Uint8Array(Math.max(0, end - begin));
    let at = begin;
    while (at < end) {
      const held = this.chunks.find((c) => c.begin <= at && at < c.begin + c.data.byteLength);
      if (held) {
        const upto = Math.min(end, held.begin + held.data.byteLength);
        out.set(held.data.subarray(at - held.begin, upto - held.begin), at - begin);
        at = upto;
        continue;
      }
      const next = Math.min(end, ...this.chunks.filter((c) => c.begin > at).map((c) => c.begin));
      const data = await this.fetchRange(at, next);
      if (!data.byteLength) break;
      out.set(data, at - begin);
      at += data.byteLength;
    }
    return out.subarray(0, at - begin);
  };
}

// A node's LAZ chunk decoded to its point records: copc.js's decompressChunk, but each point
// decoded straight into one output block of laz-perf's heap (copc.js copies every point out
// through a new view: 2-3x slower on a 30 k point node).
function decodeNode(lp, compressed, { pointDataRecordFormat, pointDataRecordLength }, pointCount) {
  const input = lp._malloc(compressed.byteLength);
  const output = lp._malloc(pointCount * pointDataRecordLength);
  const decoder = new lp.ChunkDecoder();
  try {
    lp.HEAPU8.set(compressed, input); // HEAPU8 read after the allocations (they may grow it)
    decoder.open(pointDataRecordFormat, pointDataRecordLength, input);
    for (let i = 0; i < pointCount; i += 1) decoder.getPoint(output + i * pointDataRecordLength);
    return lp.HEAPU8.slice(output, output + pointCount * pointDataRecordLength);
  } finally {
    decoder.delete();
    lp._free(input);
    lp._free(output);
  }
}

// The nodes (key -> {pointCount, pointDataOffset, pointDataLength}) whose bounds meet
// ``bounds`` ([minx, miny, maxx, maxy]; null: every node), reading only the hierarchy pages
// that do; and how many nodes with points the pages read hold.
async function nodesIn(get, copc, bounds) {
  const meets = (key) => {
    if (!bounds) return true;
    const b = Bounds.stepTo(copc.info.cube, Key.parse(key));
    return b[0] <= bounds[2] && b[3] >= bounds[0] && b[1] <= bounds[3] && b[4] >= bounds[1];
  };
  const wanted = {};
  let seen = 0;
  let pages = [copc.info.rootHierarchyPage];
  while (pages.length) {
    const read = await Promise.all(pages.map(async ({ pageOffset, pageLength }) => (
      Hierarchy.parse(await get(pageOffset, pageOffset + pageLength)))));
    pages = [];
    for (const { nodes, pages: more } of read) {
      for (const [key, node] of Object.entries(nodes)) {
        if (node.pointCount <= 0) continue;
        seen += 1;
        if (meets(key)) wanted[key] = node;
      }
      for (const [key, page] of Object.entries(more)) if (meets(key)) pages.push(page);
    }
  }
  return { wanted, seen };
}

// The byte offset in a point record of the extra-bytes field ``name`` (null without it).
function extraOffset(header, eb, name) {
  let offset = header.pointDataRecordLength - eb.reduce((sum, e) => sum + e.length, 0);
  for (const e of eb) {
    if (e.name === name) return offset;
    offset += e.length;
  }
  return null;
}

// A tree id (int64, as its two little-endian 32-bit halves) folded to the uint32 colour key
// of the server's tree_key (standgrid/serve/viewer.py): ((hi * 0x9E3779B1) ^ lo) mod 2^32,
// 1 where that is 0 for a tree, 0 only for no tree.
function treeKey(lo, hi) {
  if (lo === 0 && hi === 0) return 0;
  const key = (Math.imul(hi, 0x9e3779b1) ^ lo) >>> 0;
  return key === 0 ? 1 : key;
}

// The core points (not withheld: buffer copies of the neighbours' points are left out) of a
// COPC tile within ``bounds`` (the cell, in the tile's CRS; null: the whole tile), at most
// ``limit`` of them (every k-th beyond, as the server's cap). ``expected``: the cells
// layer's point_count, checked (meta.complete). ``tree``: {fid, id} (the exact tree_id as
// decimal text): its points are counted by their full 64-bit id (meta.tree, as the server's).
export async function streamCell({ url, bounds = null, limit, expected = null, tree = null }) {
  const t0 = performance.now();
  const reader = new RangeReader(url);
  const get = reader.get;
  const [copc, lp] = await Promise.all([reader.start().then(() => Copc.create(get)), lazPerf()]);
  const t1 = performance.now();
  const { header, eb } = copc;
  // Nodes whose cube meets the cell, widened by two steps of the coordinate lattice.
  const pad = 2 * Math.max(...header.scale);
  const query = bounds && [bounds[0] - pad, bounds[1] - pad, bounds[2] + pad, bounds[3] + pad];
  const { wanted, seen } = await nodesIn(get, copc, query);
  const t2 = performance.now();
  const names = ['X', 'Y', 'Z', 'Classification', 'Withheld'];
  const hasHeight = eb.some((e) => e.name === 'height_above_ground');
  if (hasHeight) names.push('height_above_ground');
  const treeAt = extraOffset(header, eb, 'tree_id');
  const treeLength = eb.find((e) => e.name === 'tree_id')?.length;
  if (treeAt !== null && treeLength !== 8) throw new Error(`${url}: tree_id of ${treeLength} bytes (8 expected)`);
  const chosen = tree && BigInt.asUintN(64, BigInt(tree.id));
  const [chosenLo, chosenHi] = chosen === null ? [0, 0] : [Number(chosen & 0xffffffffn), Number(chosen >> 32n)];
  let ofTree = 0;
  // The nodes' bytes fetched at once, a run of nodes adjacent in the file in one request;
  // then each node decoded from memory.
  const runs = [];
  for (const node of Object.values(wanted).sort((p, q) => p.pointDataOffset - q.pointDataOffset)) {
    const last = runs[runs.length - 1];
    const end = node.pointDataOffset + node.pointDataLength;
    if (last && node.pointDataOffset <= last.end) last.end = Math.max(last.end, end);
    else runs.push({ begin: node.pointDataOffset, end });
  }
  await Promise.all(runs.map(({ begin, end }) => get(begin, end)));
  const buffers = [];
  for (const node of Object.values(wanted)) {
    const compressed = await Copc.loadCompressedPointDataBuffer(get, node);
    buffers.push(decodeNode(lp, compressed, header, node.pointCount));
  }
  const t3 = performance.now();
  const parts = [];
  let total = 0;
  let read = 0;
  for (const buffer of buffers) {
    const view = Las.View.create(buffer, header, eb, names);
    const [x, y, z, cls, withheld] = names.slice(0, 5).map((n) => view.getter(n));
    const height = hasHeight ? view.getter('height_above_ground') : null;
    const dv = new DataView(buffer.buffer, buffer.byteOffset, buffer.byteLength);
    const n = view.pointCount;
    read += n;
    const xyz = new Float64Array(n * 3);
    const h = new Float32Array(n);
    const keys = new Uint32Array(n);
    const classes = new Uint8Array(n);
    let m = 0;
    for (let i = 0; i < n; i += 1) {
      if (withheld(i)) continue;
      xyz[m * 3] = x(i);
      xyz[m * 3 + 1] = y(i);
      xyz[m * 3 + 2] = z(i);
      h[m] = height ? height(i) : NaN;
      classes[m] = cls(i);
      if (treeAt !== null) {
        const at = i * header.pointDataRecordLength + treeAt;
        const [lo, hi] = [dv.getUint32(at, true), dv.getUint32(at + 4, true)];
        keys[m] = treeKey(lo, hi);
        if (chosen !== null && lo === chosenLo && hi === chosenHi) ofTree += 1;
      }
      m += 1;
    }
    parts.push({ m, xyz, h, keys, classes });
    total += m;
  }
  // Beyond ``limit``: ``limit`` points spread evenly over them (the server's rule).
  const capped = total > limit;
  const count = capped ? limit : total;
  const pick = (k) => (capped ? Math.floor((k * total) / limit) : k);
  const all = { xyz: new Float64Array(total * 3), h: new Float32Array(total), keys: new Uint32Array(total), classes: new Uint8Array(total) };
  let at = 0;
  for (const p of parts) {
    all.xyz.set(p.xyz.subarray(0, p.m * 3), at * 3);
    all.h.set(p.h.subarray(0, p.m), at);
    all.keys.set(p.keys.subarray(0, p.m), at);
    all.classes.set(p.classes.subarray(0, p.m), at);
    at += p.m;
  }
  const origin = [Infinity, Infinity, Infinity];
  for (let k = 0; k < count; k += 1) {
    for (let d = 0; d < 3; d += 1) origin[d] = Math.min(origin[d], all.xyz[pick(k) * 3 + d]);
  }
  if (!count) origin.fill(0);
  const xyz = new Float32Array(count * 3);
  const points = {
    xyz,
    height_above_ground: new Float32Array(count),
    tree_key: new Uint32Array(count),
    classification: new Uint8Array(count),
  };
  for (let k = 0; k < count; k += 1) {
    const j = pick(k);
    for (let d = 0; d < 3; d += 1) xyz[k * 3 + d] = all.xyz[j * 3 + d] - origin[d];
    points.height_above_ground[k] = all.h[j];
    points.tree_key[k] = all.keys[j];
    points.classification[k] = all.classes[j];
  }
  const meta = {
    total, capped, tile: url, tile_points: header.pointCount, buffer_points: header.pointCount - total,
    complete: expected === null || expected === total,
    copc: {
      bytes: reader.bytes, file_size: reader.size, requests: reader.requests,
      nodes_read: Object.keys(wanted).length, nodes: seen, points_decoded: read,
      // where the time went (ms): header and VLRs (and laz-perf's start), hierarchy, point
      // data fetched and LAZ-decoded, points read
      ms: { header: t1 - t0, hierarchy: t2 - t1, nodes: t3 - t2, points: performance.now() - t3 },
    },
  };
  if (capped) meta.stride = total / limit;
  if (chosen !== null) {
    meta.tree = { fid: tree.fid, tree_id: tree.id, key: treeKey(chosenLo, chosenHi), points: ofTree };
  }
  return { header: { count, origin, meta }, ...points };
}
