// Builds the viewer into the Python package (standgrid/serve/static), served at /viewer/.
// The build also writes build-manifest.json: the sha256 of every source file and of every
// output, so tests/test_viewer_bundle.py can tell (without Node) when the committed bundle
// no longer matches web/.
import { createHash } from 'node:crypto';
import { readdirSync, readFileSync, statSync, writeFileSync } from 'node:fs';
import { join, relative, resolve } from 'node:path';
import { defineConfig } from 'vite';

const here = resolve(import.meta.dirname);
const outDir = resolve(process.env.STANDGRID_VIEWER_OUT || join(here, '../standgrid/serve/static'));
export const MANIFEST = 'build-manifest.json';
// What the bundle is made of (node_modules is pinned by the lock file).
const SOURCES = ['index.html', 'package.json', 'package-lock.json', 'vite.config.js', 'src'];

function files(root, entry) {
  const path = join(root, entry);
  if (statSync(path).isDirectory()) {
    return readdirSync(path).sort().flatMap((name) => files(root, join(entry, name)));
  }
  return [entry.split('\\').join('/')];
}

function hashes(root, entries) {
  const out = {};
  for (const name of entries.flatMap((e) => files(root, e)).sort()) {
    out[name] = createHash('sha256').update(readFileSync(join(root, name))).digest('hex');
  }
  return out;
}

function manifest() {
  return {
    name: 'standgrid-build-manifest',
    apply: 'build',
    closeBundle() {
      const outputs = readdirSync(outDir).filter((n) => n !== MANIFEST);
      const record = { sources: hashes(here, SOURCES), outputs: hashes(outDir, outputs) };
      writeFileSync(join(outDir, MANIFEST), JSON.stringify(record, null, 1) + '\n');
      console.log(`${MANIFEST}: ${Object.keys(record.outputs).length} outputs in ${relative(here, outDir)}`);
    },
  };
}

export default defineConfig({
  base: '/viewer/',
  plugins: [manifest()],
  build: {
    outDir,
    emptyOutDir: true,
    assetsInlineLimit: 0,
    chunkSizeWarningLimit: 2000,
    reportCompressedSize: false,
  },
});
