// Opens blapose HTML reports from disk in real headless Chromium and checks that they
// work offline: no console or page errors, no request other than file:/data:/blob:,
// a 3D view that is drawn (many colours), animation, a working slider and play/pause.
//
//   node check_report.mjs REPORT.html [MORE.html ...] [--screenshot OUT.png]
//
// Chromium: $CHROMIUM or /usr/bin/chromium (run.sh installs Debian's package).
import { chromium } from "playwright-core";
import { mkdtempSync, rmSync } from "node:fs";
import { tmpdir } from "node:os";
import { join, resolve } from "node:path";
import { pathToFileURL } from "node:url";

const args = process.argv.slice(2);
let screenshot = null;
const reports = [];
for (let i = 0; i < args.length; i++) {
  if (args[i] === "--screenshot") screenshot = args[++i];
  else reports.push(args[i]);
}
if (!reports.length) {
  console.error("usage: node check_report.mjs REPORT.html [...] [--screenshot OUT.png]");
  process.exit(2);
}

const LAUNCH_ARGS = [
  "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
  "--disable-background-networking", "--disable-component-update", "--disable-sync",
];

function assert(cond, msg) {
  if (!cond) throw new Error(msg);
}

async function checkReport(context, file, shotPath) {
  const url = pathToFileURL(resolve(file)).href;
  const page = await context.newPage();
  const problems = [];
  const requests = [];
  page.on("console", (m) => { if (m.type() === "error") problems.push(`console error: ${m.text()}`); });
  page.on("pageerror", (e) => problems.push(`page error: ${e.message}`));
  page.on("request", (r) => requests.push(r.url()));
  await page.setViewportSize({ width: 1280, height: 1000 });
  await page.goto(url, { waitUntil: "load" });
  await page.waitForSelector("body[data-ready='1']", { timeout: 10000 });
  const frames = await page.evaluate(() => window.blaposeReport.frames);
  assert(frames > 1, `${file}: ${frames} frames`);
  const errorShown = await page.locator("#error").isVisible();
  assert(!errorShown, `${file}: the page shows an error: ${await page.locator("#error").textContent()}`);

  // The 3D views are drawn: many distinct colours (skeleton, grid, anti-aliasing).
  for (const id of ["view-before", "view-after"]) {
    const colours = await page.evaluate((id) => {
      const c = document.getElementById(id);
      const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
      const seen = new Set();
      for (let i = 0; i < d.length; i += 4) seen.add((d[i] << 24) ^ (d[i + 1] << 16) ^ (d[i + 2] << 8) ^ d[i + 3]);
      return seen.size;
    }, id);
    assert(colours >= 50, `${file}: #${id} has only ${colours} distinct colours (blank?)`);
  }
  // A report of placed motion draws the pelvis path.
  const hasRoot = await page.evaluate(() => Array.isArray(JSON.parse(document.getElementById("blapose-data").textContent).root));
  if (hasRoot) {
    assert(await page.locator("#path-card").isVisible(), `${file}: the pelvis path card is hidden`);
    const inked = await page.evaluate(() => {
      const c = document.getElementById("chart-path");
      const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
      let n = 0;
      for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++;
      return n;
    });
    assert(inked > 200, `${file}: the pelvis path is not drawn (${inked} pixels)`);
    const hint = await page.locator("#path-hint").textContent();
    assert(/travelled \d+\.\d+ m/.test(hint), `${file}: no distance travelled (${hint})`);
  }

  // The slider scrubs: moving it changes the frame and the label.
  const label = page.locator("#frame-label");
  const label0 = await label.textContent();
  const target = Math.floor(frames / 2);
  await page.locator("#frame").fill(String(target));
  await page.waitForFunction((t) => window.blaposeReport.frame === t, target, { timeout: 5000 });
  await page.waitForFunction((l0) => document.getElementById("frame-label").textContent !== l0, label0, { timeout: 5000 });
  const label1 = await label.textContent();
  assert(label1.includes(String(target)), `${file}: label "${label1}" does not show frame ${target}`);
  const views = page.locator(".views");
  const shotA = await views.screenshot();

  // Play: frames advance and the picture changes; pause stops it.
  await page.locator("#play").click();
  await page.waitForFunction((t) => window.blaposeReport.frame !== t, target, { timeout: 5000 });
  await page.waitForTimeout(300);
  await page.locator("#play").click();
  assert(!(await page.evaluate(() => window.blaposeReport.playing)), `${file}: pause did not stop playback`);
  const paused = await page.evaluate(() => window.blaposeReport.frame);
  await page.waitForTimeout(300);
  assert(paused === (await page.evaluate(() => window.blaposeReport.frame)), `${file}: frames advance while paused`);
  const label2 = await label.textContent();
  assert(label2 !== label1, `${file}: the frame label did not change while playing`);
  const shotB = await views.screenshot();

  // Keys: space toggles playback once, also with the play button focused.
  await page.locator("#play").focus();
  await page.keyboard.press(" ");
  assert(await page.evaluate(() => window.blaposeReport.playing), `${file}: space did not start playback`);
  await page.keyboard.press(" ");
  assert(!(await page.evaluate(() => window.blaposeReport.playing)), `${file}: space did not pause`);
  await page.evaluate(() => window.blaposeReport.setFrame(1));
  await page.locator("body").focus();
  await page.keyboard.press("ArrowRight");
  assert((await page.evaluate(() => window.blaposeReport.frame)) === 2, `${file}: the right arrow did not step a frame`);
  assert(!shotA.equals(shotB), `${file}: the views look the same after playing`);

  // Orbit: dragging one view rotates both (a shared camera).
  const yaw0 = await page.evaluate(() => window.blaposeReport.view.yaw);
  const box = await page.locator("#view-before").boundingBox();
  await page.mouse.move(box.x + box.width / 2, box.y + box.height / 2);
  await page.mouse.down();
  await page.mouse.move(box.x + box.width / 2 + 120, box.y + box.height / 2 + 30, { steps: 5 });
  await page.mouse.up();
  const yaw1 = await page.evaluate(() => window.blaposeReport.view.yaw);
  assert(Math.abs(yaw1 - yaw0) > 0.5, `${file}: dragging did not rotate the view (${yaw0} -> ${yaw1})`);
  const shotC = await views.screenshot();
  assert(!shotB.equals(shotC), `${file}: the views look the same after rotating`);

  if (shotPath) {
    await page.evaluate(() => window.blaposeReport.setFrame(Math.floor(window.blaposeReport.frames / 3)));
    await page.evaluate(() => { Object.assign(window.blaposeReport.view, { yaw: -0.6, pitch: 0.25, zoom: 1 }); window.blaposeReport.setFrame(window.blaposeReport.frame); });
    await page.screenshot({ path: shotPath, fullPage: true });
  }

  const foreign = requests.filter((u) => !/^(file|data|blob):/.test(u));
  assert(!foreign.length, `${file}: network requests: ${foreign.join(", ")}`);
  assert(!problems.length, `${file}:\n  ${problems.join("\n  ")}`);
  await page.close();
  return { frames, requests: requests.length };
}

const userDataDir = mkdtempSync(join(tmpdir(), "blapose-chromium-"));
let failed = false;
let context;
try {
  context = await chromium.launchPersistentContext(userDataDir, {
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: true,
    args: LAUNCH_ARGS,
  });
  // Anything that is not a local file fails loudly instead of waiting on a network.
  await context.route(/^(?!file:|data:|blob:)/, (route) => route.abort());
  for (const [i, file] of reports.entries()) {
    try {
      const r = await checkReport(context, file, i === 0 ? screenshot : null);
      console.log(`ok   ${file}: ${r.frames} frames, no errors, no network, drawn, animates, slider and play/pause work`);
    } catch (e) {
      failed = true;
      console.error(`FAIL ${e.message}`);
    }
  }
} finally {
  if (context) await context.close();
  rmSync(userDataDir, { recursive: true, force: true });
}
process.exit(failed ? 1 : 0);
