// Opens the web viewer of a running stack in headless Chromium, waits for tiles to stream in,
// measures a profile by clicking two points and the roughness of the view, and prints one JSON
// line with what happened. Usage: node check_viewer.mjs VIEWER_URL SCREENSHOT.png
import { writeFile } from "node:fs/promises";
import { canvasStats, launchChromium } from "./browser.mjs";

const [viewerUrl, screenshotPath] = process.argv.slice(2);
const browser = await launchChromium();
const result = { errors: [], tileRequests: 0 };
try {
  const page = await browser.newPage({ viewport: { width: 1100, height: 700 } });
  page.on("pageerror", (error) => result.errors.push(String(error)));
  const twoFrames = () => page.evaluate(() => new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(resolve))));
  page.on("request", (request) => { if (request.url().endsWith(".glb")) result.tileRequests++; });
  await page.goto(viewerUrl);
  let quiet = 0;
  for (let i = 0; i < 240 && quiet < 4; i++) {
    await page.waitForTimeout(250);
    const status = await page.evaluate(() => window.viewer?.status);
    quiet = status && status.loaded > 0 && status.downloading === 0 ? quiet + 1 : 0;
  }
  result.status = await page.evaluate(() => window.viewer.status);
  // Profile tool: two clicks across the middle of the view.
  const view = await page.locator("#view canvas").boundingBox();
  await page.click("#profile-tool");
  await page.mouse.click(view.x + view.width * 0.35, view.y + view.height * 0.5);
  await page.mouse.click(view.x + view.width * 0.65, view.y + view.height * 0.55);
  await page.waitForFunction(() => window.viewer.profile !== null, null, { timeout: 30000 });
  result.profile = await page.evaluate(() => ({
    samples: window.viewer.profile.distance_um?.length ?? 0,
    parameters: window.viewer.profile.parameters,
    text: document.getElementById("profile-stats").textContent,
  }));
  await page.click("#roughness-button");
  await page.waitForFunction(() => window.viewer.roughness !== null, null, { timeout: 120000 });  // slow on a busy machine
  result.roughness = await page.evaluate(() => window.viewer.roughness);
  result.scaleBar = await page.evaluate(() => document.getElementById("scale-label").textContent);
  await page.check("#zoom-kinds");
  await twoFrames();
  await writeFile(screenshotPath, await page.screenshot({ timeout: 60000 }));
  const background = [17, 17, 17];  // the scene's
  result.litFraction = (await canvasStats(page, "#view canvas", background)).litFraction;
  // Height colours: their spread is near 0 when every vertex gets one colour.
  await page.uncheck("#zoom-kinds");
  await page.check("input[name=colouring][value=height]");
  await twoFrames();
  result.heightColourSpread = (await canvasStats(page, "#view canvas", background)).redMinusBlueSpread;
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));
