// Opens the live page in headless Chromium whose camera is a video file
// (--use-file-for-fake-video-capture), lets it run, and checks what a person in
// front of a webcam would see: the person detected, the server answering every
// frame sent, the bone lengths settled, the skeleton drawn, no page errors and
// no request leaving the server, and the take downloads as BVH, C3D, TRC and a
// replay file. Prints window.blapose.stats as JSON.
//
//   node check_live.mjs URL VIDEO.y4m SCREENSHOT.png [SECONDS]
import { chromium } from "playwright-core";

const [url, video, shot, seconds = "25"] = process.argv.slice(2);
if (!url || !video || !shot) {
  console.error("usage: node check_live.mjs URL VIDEO.y4m SCREENSHOT.png [SECONDS]");
  process.exit(2);
}
const failures = [];
const check = (ok, what) => { if (!ok) failures.push(what); };

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: [
    "--use-fake-ui-for-media-stream",
    "--use-fake-device-for-media-stream",
    `--use-file-for-fake-video-capture=${video}`,
    "--no-sandbox",
  ],
});
const page = await browser.newPage({ viewport: { width: 1280, height: 1000 } });
const problems = [], foreign = [];
const origin = new URL(url).origin;
page.on("pageerror", (e) => problems.push(`page error: ${e.message}`));
// MediaPipe's WebAssembly writes its informational lines to stderr, which the page
// gets as console errors: "INFO: Created TensorFlow Lite XNNPACK delegate for CPU."
page.on("console", (m) => { if (m.type() === "error" && !m.text().startsWith("INFO: ")) problems.push(`console: ${m.text()}`); });
page.on("request", (r) => { if (!r.url().startsWith(origin) && !r.url().startsWith("data:") && !r.url().startsWith("blob:")) foreign.push(r.url()); });
await page.goto(url, { waitUntil: "load" });
await page.waitForFunction(() => window.blapose && window.blapose.stats.frames_answered > 0, null, { timeout: 60000 });
await page.waitForTimeout(Number(seconds) * 1000);
// Stop sending, let the frames in flight come back, then compare the counts.
await page.evaluate(() => window.blapose.pause());
await page.waitForTimeout(1500);
const stats = await page.evaluate(() => ({ ...window.blapose.stats }));
await page.screenshot({ path: shot, fullPage: true });
// The 3D view has a skeleton: dark joint pixels on the light background.
const inked = await page.evaluate(() => {
  const c = document.querySelector("#view3d canvas");
  const g = document.createElement("canvas");
  g.width = c.width; g.height = c.height;
  const ctx = g.getContext("2d");
  ctx.drawImage(c, 0, 0);
  const d = ctx.getImageData(0, 0, g.width, g.height).data;
  let n = 0;
  for (let i = 0; i < d.length; i += 4) if (d[i] + d[i + 1] + d[i + 2] < 300) n++;
  return n;
});
// The take as files, from the page's own download path (the server's writers).
const files = await page.evaluate(async () => {
  const out = {};
  for (const format of ["bvh", "c3d", "trc", "npz"]) {
    try {
      const blob = await window.blapose.exportTake(format);
      const head = new Uint8Array(await blob.slice(0, 16).arrayBuffer());
      out[format] = { bytes: blob.size, head: String.fromCharCode(...head), key: head[1] };
    } catch (e) {
      out[format] = { error: e.message };
    }
  }
  return out;
});
await browser.close();

console.log(JSON.stringify(stats));
check(stats.frames_sent >= 60, `frames sent ${stats.frames_sent} (the person was not detected?)`);
check(stats.frames_answered === stats.frames_sent, `answered ${stats.frames_answered} of ${stats.frames_sent} frames sent`);
check(stats.errors === 0, `${stats.errors} errors (last: ${stats.last_error})`);
const minFps = Number(process.env.BLAPOSE_LIVE_MIN_FPS ?? 15), maxP99 = Number(process.env.BLAPOSE_LIVE_MAX_P99_MS ?? 100);
check(stats.fps >= minFps, `${stats.fps} frames/s answered (at least ${minFps})`);
check(stats.latency_p99_ms != null && stats.latency_p99_ms <= maxP99, `capture-to-answer p99 ${stats.latency_p99_ms} ms (at most ${maxP99})`);
check(stats.lengths_std_mm_last_50 != null && stats.lengths_std_mm_last_50 <= 1, `bone lengths' std over the last 50 frames ${stats.lengths_std_mm_last_50} mm (at most 1)`);
check(Array.isArray(stats.lengths_m) && stats.lengths_m.length === 16, "no bone lengths");
check(inked > 300, `the 3D view shows no skeleton (${inked} dark pixels)`);
console.log(JSON.stringify(files));
check(files.bvh.head?.startsWith("HIERARCHY"), `the take as BVH: ${JSON.stringify(files.bvh)}`);
check(files.c3d.key === 0x50 && files.c3d.bytes > 512, `the take as C3D: ${JSON.stringify(files.c3d)}`);
check(files.trc.head?.startsWith("PathFileType"), `the take as TRC: ${JSON.stringify(files.trc)}`);
check(files.npz.head?.startsWith("PK"), `the take as a replay file: ${JSON.stringify(files.npz)}`);
check(!foreign.length, `requests leaving the server: ${foreign.join(", ")}`);
check(!problems.length, problems.join("\n  "));
if (failures.length) {
  for (const f of failures) console.error(`FAILED: ${f}`);
  process.exit(1);
}
console.log(`ok   ${url}: ${stats.frames_answered} frames answered at ${stats.fps} frames/s, p50 ${stats.latency_p50_ms.toFixed(1)} ms, p99 ${stats.latency_p99_ms.toFixed(1)} ms, lengths settled within ${stats.lengths_std_mm_last_50.toFixed(2)} mm`);
