// Where the page's main thread spends its time while it opens a scene: a CPU profile of the
// page (Chrome DevTools Protocol) from loading until the working set is complete and drawn,
// summed by function (self time), in the test browser (chromium, SwiftShader WebGPU).
//
//   node profile.mjs URL [--top 30] [--from MS] [--to MS] [--width 960 --height 540]
//                        [--callers TEXT]
//
// Prints the page's timings and the functions with the most self time, one per line; with
// `--callers`, the self time of functions whose name contains TEXT by the function that
// called them.
import { chromium } from 'playwright-core';

const argv = process.argv.slice(2);
const url = argv[0];
const opt = (name, def) => { const i = argv.indexOf(name); return i < 0 ? def : argv[i + 1]; };
const width = Number(opt('--width', 960)), height = Number(opt('--height', 540));
const top = Number(opt('--top', 30));
// Only samples from `--from` to `--to` milliseconds after the profile started.
const from = Number(opt('--from', 0)), to = Number(opt('--to', 1e12));
const callers = opt('--callers', null);

const browser = await chromium.launch({
  executablePath: process.env.BRICKCAST_CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--disable-gpu-sandbox', '--ignore-gpu-blocklist',
    '--enable-unsafe-webgpu', '--use-angle=vulkan', '--enable-features=Vulkan',
    '--use-vulkan=swiftshader', '--use-webgpu-adapter=swiftshader'],
});
const page = await browser.newPage({ viewport: { width, height } });
page.on('pageerror', (e) => process.stderr.write(`[page error] ${e}\n`));
const cdp = await page.context().newCDPSession(page);
await cdp.send('Profiler.enable');
await cdp.send('Profiler.setSamplingInterval', { interval: 500 });
await cdp.send('Profiler.start');
await page.goto(url);
await page.waitForFunction(() => window.brickcast && JSON.parse(window.brickcast.state()).synced_ms !== null, null, { timeout: 600000, polling: 100 });
const { profile } = await cdp.send('Profiler.stop');
const s = JSON.parse(await page.evaluate(() => window.brickcast.state()));
console.log(JSON.stringify({ welcome_ms: s.welcome_ms, gpu_ready_ms: s.gpu_ready_ms, first_picture_ms: s.first_picture_ms, synced_ms: s.synced_ms, bricks: s.bricks, bytes_in: s.bytes_in, uploaded: s.uploaded }));

// Self time per function: each sample's node, weighted by its time delta.
const byId = new Map(profile.nodes.map((n) => [n.id, n]));
const parentOf = new Map();
for (const n of profile.nodes) for (const c of n.children || []) parentOf.set(c, n);
const nameOf = (n) => n.callFrame.functionName || `(anonymous ${n.callFrame.url.split('/').pop()}:${n.callFrame.lineNumber})`;
const self = new Map();
let total = 0;
let at = 0;
profile.samples.forEach((id, i) => {
  const dt = profile.timeDeltas[i] || 0;
  at += dt;
  if (at / 1000 < from || at / 1000 > to) return;
  const node = byId.get(id);
  let name = nameOf(node);
  if (callers !== null) {
    if (!name.includes(callers)) return;
    const parent = parentOf.get(id);
    name = `${name.slice(0, 60)} <- ${parent ? nameOf(parent) : '(root)'}`;
  }
  self.set(name, (self.get(name) || 0) + dt);
  total += dt;
});
const rows = [...self.entries()].sort((a, b) => b[1] - a[1]).slice(0, top);
console.log(`total sampled ${(total / 1000).toFixed(0)} ms`);
for (const [name, us] of rows) console.log(`${(us / 1000).toFixed(0).padStart(7)} ms ${(100 * us / total).toFixed(1).padStart(5)}%  ${name.slice(0, 140)}`);
await browser.close();
