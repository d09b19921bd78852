// How the page opens a scene, as it happens: every change of its state (bricks, stand-ins,
// frames, bytes, GPU bytes, first picture, synced) with the time since loading began, and the
// first websocket frames as the browser's network layer saw them (Chrome DevTools Protocol),
// in the test browser (chromium, SwiftShader WebGPU). Stops once the page is synced.
//
//   node timeline.mjs URL
import { chromium } from 'playwright-core';
const url = process.argv[2];
const browser = await chromium.launch({
  executablePath: process.env.BRICKCAST_CHROMIUM || '/usr/bin/chromium',
  args: ['--headless=new', '--no-sandbox', '--disable-gpu-sandbox', '--ignore-gpu-blocklist',
    '--enable-unsafe-webgpu', '--use-angle=vulkan', '--enable-features=Vulkan',
    '--use-vulkan=swiftshader', '--use-webgpu-adapter=swiftshader'],
});
const page = await browser.newPage({ viewport: { width: 960, height: 540 } });
const cdp = await page.context().newCDPSession(page);
await cdp.send('Network.enable');
let frames = 0, wsbytes = 0, firstBig = null, t0ws = null;
cdp.on('Network.webSocketFrameReceived', (e) => {
  frames++; wsbytes += e.response.payloadData.length;
  if (t0ws === null) t0ws = e.timestamp;
  if (frames <= 4 || (firstBig === null && e.response.payloadData.length > 1000)) {
    console.log(`ws frame ${frames} at +${((e.timestamp - t0ws) * 1000).toFixed(0)} ms after the first, ${Date.now() - t0} ms wall, ${e.response.payloadData.length} chars`);
    if (e.response.payloadData.length > 1000) firstBig = e.timestamp;
  }
});
const t0 = Date.now();
await page.goto(url);
let last = '';
for (;;) {
  const s = await page.evaluate(() => window.brickcast ? JSON.parse(window.brickcast.state()) : null);
  if (s) {
    const line = `bricks ${s.bricks} frames ${s.frames} gpu_frames ${s.gpu_frames} bytes ${s.bytes_in} first ${s.first_picture_ms} synced ${s.synced_ms} gpu_bytes ${s.gpu_bytes} stand_ins ${s.stand_ins} uploaded ${JSON.stringify(s.uploaded)}`;
    if (line !== last) { console.log(`${Date.now() - t0} ms: ${line}`); last = line; }
    if (s.synced_ms !== null) break;
  }
  await new Promise((r) => setTimeout(r, 100));
}
await browser.close();
