// The viewer on a specimen's overview as a first session sees it, in a 1280 x 800 window with the
// default error target: how many tiles the first view requests and how long it takes to settle;
// then a profile across it (its line on the surface), the light turned round, and the height
// colour map with its colour bar. Prints one JSON line; screenshots go to OUT_DIR.
// Usage: node pollen_overview.mjs VIEWER_URL OUT_DIR SETTLE_TIMEOUT_S
import { writeFile } from "node:fs/promises";
import { join } from "node:path";
import {
  addPageHelpers, canvasDifference, canvasStats, clickView, countColour, launchChromium, setControl, twoFrames, waitUntilSettled,
} from "./browser.mjs";

const [viewerUrl, outDir, timeoutS] = process.argv.slice(2);
const browser = await launchChromium();
const result = { errors: [], tileRequests: 0 };
const screenshot = async (page, name) => writeFile(join(outDir, name), await page.screenshot({ timeout: 60000 }));
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  await addPageHelpers(page);
  page.on("pageerror", (error) => result.errors.push(String(error)));
  page.on("console", (message) => { if (message.type() === "error") result.errors.push(message.text()); });
  page.on("request", (request) => { if (new URL(request.url()).pathname.endsWith(".glb")) result.tileRequests++; });
  const started = Date.now();
  await page.goto(viewerUrl);
  result.status = await waitUntilSettled(page, Number(timeoutS) * 1000);
  result.settleS = (Date.now() - started) / 1000;
  result.firstViewRequests = result.tileRequests;
  await screenshot(page, "overview.png");
  const canvas = "#view canvas";

  // A profile across the middle of the view: its line is drawn on the surface (red, #ff3355).
  const redBefore = await countColour(page, canvas, [255, 51, 85]);
  await page.click("[data-tool=profile]");
  await clickView(page, [[0.36, 0.5], [0.64, 0.45]]);  // across the grain
  await page.waitForFunction(() => window.viewer.profile !== null && !window.viewer.measurements.pending, null, { timeout: 60000 });
  await twoFrames(page);
  result.profileLinePixels = (await countColour(page, canvas, [255, 51, 85])) - redBefore;
  result.profile = await page.evaluate(() => ({
    samples: window.viewer.profile.distance_um?.length ?? 0, known: window.viewer.profile.z_um.filter((z) => z !== null).length,
    text: window.viewer.measurements.items.at(-1).text,
  }));
  await screenshot(page, "profile.png");

  // The light from the east, then from the west: the shading follows.
  await setControl(page, "#light-elevation", 30);
  await setControl(page, "#light-azimuth", 90);
  await screenshot(page, "light-east.png");
  result.lightChange = await canvasDifference(page, canvas, () => setControl(page, "#light-azimuth", 270));
  await setControl(page, "#lighting", 0);
  result.unlitChange = await canvasDifference(page, canvas, () => setControl(page, "#light-azimuth", 90));
  await setControl(page, "#light-azimuth", 270);
  await setControl(page, "#lighting", 0.7);
  await screenshot(page, "light-west.png");

  // Height colours and their bar.
  await setControl(page, "input[name=colouring][value=height]", true);
  await twoFrames(page);
  result.colourBar = await page.evaluate(() => ({
    hidden: document.getElementById("colour-bar").hidden,
    min: document.getElementById("colour-bar-min")?.textContent,
    max: document.getElementById("colour-bar-max")?.textContent,
    ticks: [...document.querySelectorAll("#colour-bar-ticks span")].map((s) => s.textContent),
    datum: document.getElementById("colour-bar-datum").textContent,
    rangeUm: window.viewer.measurements.specimen().heightRangeUm,
  }));
  result.heightColourSpread = (await canvasStats(page, canvas, [17, 17, 17])).redMinusBlueSpread;
  await screenshot(page, "height-colours.png");
  result.finalStatus = await page.evaluate(() => window.viewer.status);
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));
