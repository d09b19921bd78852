// The browser viewer's numbers for BENCHMARKS.md, in the test browser (chromium, SwiftShader
// WebGPU): time to first picture and to full sync after opening the page, GPU frame time at each
// resolution divisor, and (with soak) the page's memory over a long session.
//
//   node bench.mjs URL [--width 960 --height 540] [--soak SECONDS] [--screenshot FILE]
//
// Prints one JSON object. Times are milliseconds since the page started loading.
import { chromium } from 'playwright-core';

const argv = process.argv.slice(2);
const url = argv[0];
const opt = (name, def) => { const i = argv.indexOf(name); return i < 0 ? def : argv[i + 1]; };
const width = Number(opt('--width', 960)), height = Number(opt('--height', 540));
const soak = Number(opt('--soak', 0));
const shot = opt('--screenshot', null);
const camera = opt('--camera', null); // "ex,ey,ez,tx,ty,tz"

const browser = await chromium.launch({
  executablePath: process.env.BRICKCAST_CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--disable-gpu-sandbox', '--ignore-gpu-blocklist',
    '--enable-unsafe-webgpu', '--use-angle=vulkan', '--enable-features=Vulkan',
    '--use-vulkan=swiftshader', '--use-webgpu-adapter=swiftshader', '--enable-precise-memory-info'],
});
const page = await browser.newPage({ viewport: { width, height } });
page.on('pageerror', (e) => process.stderr.write(`[page error] ${e}\n`));
const state = async () => JSON.parse(await page.evaluate(() => window.brickcast ? window.brickcast.state() : 'null'));
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const out = { url, width, height };

await page.goto(url);
await page.waitForFunction(() => window.brickcast && JSON.parse(window.brickcast.state()).first_picture_ms !== null, null, { timeout: 120000, polling: 50 });
await page.waitForFunction(() => JSON.parse(window.brickcast.state()).synced_ms !== null, null, { timeout: 600000, polling: 100 });
let s = await state();
Object.assign(out, { started_ms: s.started_ms, gpu_ready_ms: s.gpu_ready_ms, welcome_ms: s.welcome_ms, first_picture_ms: s.first_picture_ms, synced_ms: s.synced_ms, bricks: s.bricks, adapter: s.adapter, bytes_in: s.bytes_in });
if (camera) {
  const c = camera.split(',').map(Number);
  await page.evaluate((c) => window.brickcast.set_camera(new Float32Array(c.slice(0, 3)), new Float32Array(c.slice(3))), c);
}

// GPU time per frame at each divisor (pinned), then where the automatic scale settles.
out.frames = [];
// GPU time of `n` frames finished after the ones in flight (each frame is submitted only when
// the previous one finished, so these are whole frames: trace, overlay, blit).
const frameTimes = async (n) => {
  let seen = (await state()).gpu_frames + 2;
  const times = [];
  while (times.length < n) {
    await sleep(20);
    const s = await state();
    if (s.gpu_frames > seen) { seen = s.gpu_frames; times.push(s.gpu_last_ms); }
  }
  times.sort((a, b) => a - b);
  return times[Math.floor(n / 2)];
};
for (const divisor of [1, 2, 4, 8]) {
  await page.evaluate((d) => window.brickcast.set_scale(d), divisor);
  const ms = await frameTimes(7);
  const w = Math.ceil(width / divisor), h = Math.ceil(height / divisor);
  out.frames.push({ divisor, trace_width: w, trace_height: h, frame_ms_median: ms, mrays_per_s: w * h / ms / 1000 });
}
await page.evaluate(() => window.brickcast.set_scale(0));
await sleep(6000);
s = await state();
out.auto = { divisor: s.divisor, gpu_ms: s.gpu_ms, fps: s.fps };
if (shot) {
  await page.evaluate(() => window.brickcast.set_scale(1));
  await sleep(3000);
  await page.screenshot({ path: shot });
  await page.evaluate(() => window.brickcast.set_scale(0));
}

if (soak > 0) {
  const memory = async () => page.evaluate(() => ({
    wasm_bytes: window.brickcast.wasm_memory_bytes(),
    js_heap_bytes: performance.memory ? performance.memory.usedJSHeapSize : null,
    state: JSON.parse(window.brickcast.state()),
  }));
  out.soak = [];
  const start = Date.now();
  while (Date.now() - start < soak * 1000) {
    const m = await memory();
    out.soak.push({ t_s: Math.round((Date.now() - start) / 1000), wasm_bytes: m.wasm_bytes, js_heap_bytes: m.js_heap_bytes, seq: m.state.seq, bricks: m.state.bricks, scene_bytes: m.state.scene_bytes, status: m.state.status });
    await sleep(Math.min(30000, soak * 1000 / 10));
  }
  const m = await memory();
  out.soak.push({ t_s: soak, wasm_bytes: m.wasm_bytes, js_heap_bytes: m.js_heap_bytes, seq: m.state.seq, bricks: m.state.bricks, scene_bytes: m.state.scene_bytes, status: m.state.status });
}
console.log(JSON.stringify(out, null, 1));
await browser.close();
