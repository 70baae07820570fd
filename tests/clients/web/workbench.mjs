// The viewer as issue 38 asks for it, on one specimen: the console stays clean; the orthographic
// top view shows a scale bar, the perspective and side views none; the bar's length against the
// surface on screen (its extent, and two points picked a bar's length apart); numbers without
// exponents; the snapshot's texts inside the picture; the specimen list with thumbnails.
// Prints one JSON line; screenshots go to OUT_DIR.
// Usage: node workbench.mjs BASE_URL SPECIMEN OUT_DIR
import { writeFile } from "node:fs/promises";
import { join } from "node:path";
import { addPageHelpers, clickView, launchChromium, setControl, twoFrames, waitUntilSettled } from "./browser.mjs";

const [baseUrl, specimenId, outDir] = process.argv.slice(2);
const browser = await launchChromium();
const result = { console: [] };
const background = [17, 17, 17]; // the scene's
const screenshot = async (page, name) => writeFile(join(outDir, name), await page.screenshot({ timeout: 60000 }));
const scaleBar = (page) => page.evaluate(() => ({
  hidden: document.getElementById("scale-bar").hidden, hintShown: !document.getElementById("scale-hint").hidden,
  label: document.getElementById("scale-label").textContent, lengthPx: document.getElementById("scale-line").getBoundingClientRect().width,
}));
// The widest run of surface pixels in any row of the 3D view, CSS px.
const surfaceWidthPx = (page) => page.evaluate((background) => {
  const canvas = document.querySelector("#view canvas");
  const pixels = window.__pixels("#view canvas");
  const ratio = canvas.width / canvas.clientWidth;
  let widest = 0;
  for (let row = 0; row < canvas.height; row++) {
    let first = -1, last = -1;
    for (let col = 0; col < canvas.width; col++) {
      const i = 4 * (row * canvas.width + col);
      if (Math.abs(pixels[i] - background[0]) + Math.abs(pixels[i + 1] - background[1]) + Math.abs(pixels[i + 2] - background[2]) > 30) {
        if (first < 0) first = col;
        last = col;
      }
    }
    if (first >= 0) widest = Math.max(widest, last - first + 1);
  }
  return widest / ratio;
}, background);

try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  await addPageHelpers(page);
  page.on("console", (message) => { if (["warning", "error"].includes(message.type())) result.console.push(`${message.type()}: ${message.text()}`); });
  page.on("pageerror", (error) => result.console.push(`pageerror: ${error}`));
  await page.goto(`${baseUrl}/viewer/?specimen=${specimenId}`);
  await waitUntilSettled(page, 300000);
  result.perspectiveBar = await scaleBar(page);
  result.list = await page.evaluate(() => [...document.querySelectorAll("#specimens .specimen")].map((entry) => ({
    id: entry.dataset.specimen, current: entry.classList.contains("current"), state: entry.querySelector(".specimen-state").textContent,
    thumbnailPx: entry.querySelector("img")?.naturalWidth ?? 0,
  })));
  await screenshot(page, "perspective.png");

  // Orthographic (key O), from above (key T).
  await page.keyboard.press("o");
  await page.keyboard.press("t");
  await waitUntilSettled(page, 300000);
  result.projection = await page.evaluate(() => document.getElementById("projection").value);
  result.topBar = await scaleBar(page);
  result.surfaceWidthPx = await surfaceWidthPx(page);
  await screenshot(page, "top.png");
  // Two points a bar's length apart across the middle, picked on the surface with the distance tool.
  const view = await page.locator("#view canvas").boundingBox();
  const half = result.topBar.lengthPx / 2 / view.width;
  await page.click("[data-tool=distance]");
  await clickView(page, [[0.5 - half, 0.5], [0.5 + half, 0.5]]);
  await page.waitForFunction(() => window.viewer.measurements.items.length === 1 && !window.viewer.measurements.pending, null, { timeout: 60000 });
  result.pickedHorizontalUm = await page.evaluate(() => window.viewer.measurements.items[0].result?.horizontal_um ?? null);

  // The same view in perspective, then from the side (orthographic): no bar in either.
  await page.selectOption("#projection", "perspective");
  await twoFrames(page);
  result.topPerspectiveBar = await scaleBar(page);
  await page.selectOption("#projection", "orthographic");
  await page.click("[data-view=side]");
  await waitUntilSettled(page, 300000);
  result.sideBar = await scaleBar(page);
  await screenshot(page, "side.png");
  await page.click("[data-view=front]");
  await waitUntilSettled(page, 300000);
  await screenshot(page, "front.png");
  await page.click("[data-view=start]");
  await waitUntilSettled(page, 300000);
  result.resetDirection = await page.evaluate(() => {
    const { camera, controls } = window.viewer.debug;
    return camera.position.clone().sub(controls.target).normalize().toArray();
  });

  // Every number on the page with a profile, the roughness of the view and the height colours.
  await page.click("[data-view=top]");
  await waitUntilSettled(page, 300000);
  await page.click("[data-tool=profile]");
  await clickView(page, [[0.3, 0.5], [0.7, 0.45]]);
  await page.waitForFunction(() => window.viewer.measurements.items.length === 2 && !window.viewer.measurements.pending, null, { timeout: 60000 });
  await page.click("#roughness-button");
  await page.waitForFunction(() => window.viewer.roughness !== null, null, { timeout: 300000 });
  await setControl(page, "input[name=colouring][value=height]", true);
  result.roughness = await page.evaluate(() => ({ text: document.getElementById("roughness-stats").textContent, pixelSizeUm: window.viewer.roughness.pixel_size_um }));
  result.pageText = await page.evaluate(() => document.body.innerText);
  result.formatted = await page.evaluate(async () => {
    const { formatNumber, formatUm } = await import("/viewer/plot.js");
    const values = [];
    for (let exponent = -3; exponent <= 5; exponent += 0.01) values.push(10 ** exponent, -(10 ** exponent), 1.2 * 10 ** Math.round(exponent));
    return values.filter((v) => Math.abs(v) >= 1e-3 && Math.abs(v) <= 1e5).flatMap((v) => [1, 2, 3, 4].map((digits) => formatNumber(v, digits)).concat(formatUm(v)));
  });
  await screenshot(page, "numbers.png");
  const snapshot = await page.evaluate(() => window.viewer.snapshot());
  await writeFile(join(outDir, "snapshot.png"), Buffer.from(snapshot.split(",")[1], "base64"));
  result.snapshotTexts = await page.evaluate(() => window.viewer.snapshotTexts);
  result.viewWidthPx = view.width;
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));
