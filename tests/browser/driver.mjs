// Drives a real browser for the browser viewer's tests: Debian's chromium through
// playwright-core, with software WebGPU (SwiftShader). The Rust test sends one JSON command per
// line on stdin and reads one JSON answer per line on stdout; the page's console goes to stderr.
//
//   node driver.mjs '{"webgpu": true}'
//
// Commands: {op: "goto", url} · {op: "wait", js, timeout_ms} (until js is truthy) ·
// {op: "eval", js} · {op: "click", x, y, button, modifiers} · {op: "drag", from: [x, y],
// to: [x, y], button} · {op: "key", key} ·
// {op: "screenshot", path} · {op: "close"}
import { chromium } from 'playwright-core';
import readline from 'node:readline';

const options = JSON.parse(process.argv[2] || '{}');
const args = ['--headless=new', '--no-sandbox', '--disable-gpu-sandbox', '--ignore-gpu-blocklist'];
if (options.webgpu !== false) {
  // WebGPU on SwiftShader, presenting to a canvas through ANGLE's Vulkan on SwiftShader.
  args.push('--enable-unsafe-webgpu', '--use-angle=vulkan', '--enable-features=Vulkan',
    '--use-vulkan=swiftshader', '--use-webgpu-adapter=swiftshader');
} else {
  // A browser without WebGPU, as many still are.
  args.push('--disable-features=WebGPU', '--disable-webgpu');
}
const browser = await chromium.launch({
  executablePath: process.env.BRICKCAST_CHROMIUM || '/usr/bin/chromium',
  args,
});
const page = await browser.newPage({ viewport: options.viewport || { width: 320, height: 180 } });
// Errors only: shader compilers log warnings on every page load.
page.on('console', (m) => { if (m.type() === 'error') process.stderr.write(`[page ${m.type()}] ${m.text()}\n`); });
page.on('pageerror', (e) => process.stderr.write(`[page error] ${e}\n`));

async function run(cmd) {
  switch (cmd.op) {
    case 'goto':
      await page.goto(cmd.url, { waitUntil: 'load' });
      return page.url();
    case 'wait':
      await page.waitForFunction(cmd.js, null, { timeout: cmd.timeout_ms ?? 30000, polling: 100 });
      return await page.evaluate(cmd.js);
    case 'eval':
      return await page.evaluate(cmd.js);
    case 'click':
      for (const m of cmd.modifiers ?? []) await page.keyboard.down(m);
      await page.mouse.click(cmd.x, cmd.y, { button: cmd.button ?? 'left' });
      for (const m of cmd.modifiers ?? []) await page.keyboard.up(m);
      return null;
    case 'drag':
      await page.mouse.move(cmd.from[0], cmd.from[1]);
      await page.mouse.down({ button: cmd.button ?? 'left' });
      await page.mouse.move(cmd.to[0], cmd.to[1], { steps: 8 });
      await page.mouse.up({ button: cmd.button ?? 'left' });
      return null;
    case 'key':
      await page.keyboard.press(cmd.key);
      return null;
    case 'screenshot':
      await page.screenshot({ path: cmd.path });
      return cmd.path;
    case 'close':
      await browser.close();
      process.exit(0);
    default:
      throw new Error(`unknown op ${cmd.op}`);
  }
}

const lines = readline.createInterface({ input: process.stdin });
console.log(JSON.stringify({ ok: true, result: 'ready' }));
for await (const line of lines) {
  if (!line.trim()) continue;
  try {
    const result = await run(JSON.parse(line));
    console.log(JSON.stringify({ ok: true, result: result ?? null }));
  } catch (e) {
    console.log(JSON.stringify({ ok: false, error: String(e && e.message || e) }));
  }
}
await browser.close();
