// The web viewer's tools on a running stack in headless Chromium: a link to a specimen that does
// not exist, tiles streaming in with their counter, the optical/digital legend and the ROI labels,
// every measuring tool, two profiles in one plot, the vertical exaggeration, the roughness of the
// view, styles (colouring, optical/digital shading) that reach tiles cached outside the scene, the
// permalink and the PNG snapshot. Prints one JSON line; screenshots go to OUT_DIR.
// Usage: node check_viewer.mjs BASE_URL SPECIMEN OUT_DIR
import { writeFile } from "node:fs/promises";
import { join } from "node:path";
import { addPageHelpers, canvasDifference, canvasStats, clickView, countColour, launchChromium, setControl, twoFrames, waitUntilSettled } from "./browser.mjs";

const [baseUrl, specimenId, outDir] = process.argv.slice(2);
const browser = await launchChromium();
const result = { errors: [], tileRequests: 0 };
const background = [17, 17, 17]; // the scene's
const canvas = "#view canvas";

async function newPage() {
  const page = await browser.newPage({ viewport: { width: 1100, height: 700 } });
  await addPageHelpers(page);
  page.on("pageerror", (error) => result.errors.push(String(error)));
  page.on("request", (request) => { if (new URL(request.url()).pathname.endsWith(".glb")) result.tileRequests++; });
  return page;
}

async function measure(page, tool, fractions) {
  const before = await page.evaluate(() => window.viewer.measurements.items.length);
  await page.click(`[data-tool=${tool}]`);
  await clickView(page, fractions);
  try {
    await page.waitForFunction((count) => window.viewer.measurements.items.length === count + 1 && !window.viewer.measurements.pending, before, { timeout: 60000 });
  } catch (error) {
    throw new Error(`${tool} did not finish: ${JSON.stringify(await page.evaluate(() => ({ tool: window.viewer.measurements.tool, picked: window.viewer.measurements.picked, missed: window.viewer.status.missedPicks, items: window.viewer.measurements.items.map((i) => i.text) })))}`);
  }
  return page.evaluate(() => window.viewer.measurements.items.at(-1).text);
}

try {
  // A link to a specimen that is not there: an error, and no other specimen opened instead.
  const missing = await newPage();
  await missing.goto(`${baseUrl}/viewer/?specimen=doesnotexist`);
  await missing.waitForFunction(() => window.viewer?.status?.error, null, { timeout: 30000 });
  result.missing = await missing.evaluate(() => ({
    error: window.viewer.status.error, message: document.getElementById("message").textContent,
    shown: !document.getElementById("message").hidden, chosen: document.querySelector("#specimens .current")?.dataset.specimen ?? "",
  }));
  result.missingTileRequests = result.tileRequests;
  await writeFile(join(outDir, "missing.png"), await missing.screenshot());
  await missing.close();

  const page = await newPage();
  await page.goto(`${baseUrl}/viewer/?specimen=${specimenId}`);
  result.status = await waitUntilSettled(page, 120000);
  await page.check("#zoom-kinds");
  await twoFrames(page);
  result.litFraction = (await canvasStats(page, canvas, background)).litFraction;
  await writeFile(join(outDir, "viewer.png"), await page.screenshot({ timeout: 60000 }));
  result.overlays = await page.evaluate(() => ({
    legend: document.getElementById("legend").textContent, tileProgress: document.getElementById("tile-progress-text").textContent,
    roiLabels: [...document.querySelectorAll("#roi-labels span")].filter((label) => label.style.display !== "none").map((label) => label.textContent),
  }));
  await page.uncheck("#zoom-kinds");
  result.overlays.legendAfter = await page.evaluate(() => document.getElementById("legend").textContent);

  // Every tool, measured where the view shows the surface.
  const redBefore = await countColour(page, canvas, [255, 51, 85]);
  result.tools = {
    profile: await measure(page, "profile", [[0.35, 0.5], [0.65, 0.55]]),
    point: await measure(page, "point", [[0.5, 0.5]]),
    distance: await measure(page, "distance", [[0.4, 0.4], [0.6, 0.6]]),
    angle: await measure(page, "angle", [[0.4, 0.6], [0.5, 0.45], [0.6, 0.6]]),
    step: await measure(page, "step", [[0.35, 0.35], [0.45, 0.45], [0.55, 0.55], [0.65, 0.65]]),
  };
  await twoFrames(page);
  result.profileLinePixels = (await countColour(page, canvas, [255, 51, 85])) - redBefore;
  result.profile = await page.evaluate(() => ({
    samples: window.viewer.profile.distance_um?.length ?? 0, parameters: window.viewer.profile.parameters,
    text: window.viewer.measurements.items[0].text,
  }));
  // A second profile: both drawn in the one plot, each in its own colour.
  result.tools.secondProfile = await measure(page, "profile", [[0.35, 0.6], [0.65, 0.4]]);
  const profileColours = await page.evaluate(() => window.viewer.measurements.items.filter((item) => item.tool === "profile").map((item) => item.colour));
  result.plotted = [];
  for (const colour of profileColours) {
    const rgb = [1, 3, 5].map((i) => parseInt(colour.slice(i, i + 2), 16));
    result.plotted.push({ colour, pixels: await countColour(page, "#profile-plot", rgb, 30) });
  }
  await writeFile(join(outDir, "measurements.png"), await page.screenshot({ timeout: 60000 }));
  // Heights 10x: the picture changes; back to 1x, and the levels it refined settle.
  result.exaggerationChange = await canvasDifference(page, canvas, () => setControl(page, "#exaggeration", 1));
  result.exaggerationShown = await page.evaluate(() => document.getElementById("exaggeration-value").textContent);
  await setControl(page, "#exaggeration", 0);
  await waitUntilSettled(page, 120000);

  await page.click("#roughness-button");
  result.roughnessBusy = await page.evaluate(() => document.getElementById("roughness-button").classList.contains("busy"));
  await page.waitForFunction(() => window.viewer.roughness !== null, null, { timeout: 120000 });  // slow on a busy machine
  result.roughness = await page.evaluate(() => window.viewer.roughness);
  result.roughnessText = await page.evaluate(() => document.getElementById("roughness-stats").textContent);
  result.scaleBar = await page.evaluate(() => ({ hidden: document.getElementById("scale-bar").hidden, hint: !document.getElementById("scale-hint").hidden }));

  // Height colours, then closer in (tiles of the overview drop out of the scene into the cache),
  // back to the SEM image there, and out again: the cached tiles come back with the new style.
  await setControl(page, "input[name=colouring][value=height]", true);
  result.heightColourSpread = (await canvasStats(page, canvas, background)).redMinusBlueSpread;
  const zoom = (factor) => page.evaluate((factor) => {
    const { camera, controls } = window.viewer.debug;
    camera.position.sub(controls.target).multiplyScalar(factor).add(controls.target);
    controls.update();
  }, factor);
  await zoom(0.15);
  await waitUntilSettled(page, 120000);
  await setControl(page, "input[name=colouring][value=texture]", true);
  await zoom(1 / 0.15);
  await waitUntilSettled(page, 120000);
  result.restyledSpread = (await canvasStats(page, canvas, background)).redMinusBlueSpread;
  // Likewise the optical/digital shading switched on close in: the cached tiles come back tinted.
  const tinted = () => page.evaluate(([selector, background]) => {
    const pixels = window.__pixels(selector);
    let surface = 0, shaded = 0;
    for (let i = 0; i < pixels.length; i += 4) {
      const [r, g, b] = [pixels[i], pixels[i + 1], pixels[i + 2]];
      if (Math.abs(r - background[0]) + Math.abs(g - background[1]) + Math.abs(b - background[2]) <= 30) continue;
      surface++;
      if (g > 1.3 * Math.max(r, b, 1) || (r > 1.3 * Math.max(b, 1) && r > g)) shaded++; // optical green or digital orange
    }
    return shaded / Math.max(surface, 1);
  }, [canvas, background]);
  result.tintedBefore = await tinted();
  await zoom(0.15);
  await waitUntilSettled(page, 120000);
  await page.check("#zoom-kinds");
  await zoom(1 / 0.15);
  await waitUntilSettled(page, 120000);
  result.tintedAfter = await tinted();
  await page.uncheck("#zoom-kinds");

  // The permalink opens the same view with the same measurements.
  const link = await page.evaluate(() => { document.getElementById("permalink").click(); return document.getElementById("permalink-text").value; });
  result.permalink = link;
  result.snapshot = await page.evaluate(() => window.viewer.snapshot());
  await writeFile(join(outDir, "snapshot.png"), Buffer.from(result.snapshot.split(",")[1], "base64"));
  result.snapshot = result.snapshot.slice(0, 30);
  const cameraOf = (p) => p.evaluate(() => window.viewer.debug.camera.position.toArray());
  result.camera = await cameraOf(page);
  const reopened = await newPage();
  await reopened.goto(link);
  await waitUntilSettled(reopened, 120000);
  await reopened.waitForFunction((count) => window.viewer.measurements.items.length === count && !window.viewer.measurements.pending,
    await page.evaluate(() => window.viewer.measurements.items.length), { timeout: 60000 });
  result.reopened = {
    camera: await cameraOf(reopened),
    tools: await reopened.evaluate(() => window.viewer.measurements.items.map((item) => item.text)),
  };
  await writeFile(join(outDir, "permalink.png"), await reopened.screenshot({ timeout: 60000 }));
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));
