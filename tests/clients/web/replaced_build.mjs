// A specimen rebuilt while the viewer shows it: the page settles on the old build, writes
// READY_FILE and waits for GO_FILE (the test replaces the build meanwhile), then zooms in, so that
// tiles of the old build are asked for (410 Gone). Prints one JSON line: how often the viewer
// opened the specimen again, its status once settled, the camera's position before and after,
// and the console's warnings and errors (the 410s' own lines aside).
// Usage: node replaced_build.mjs BASE_URL SPECIMEN READY_FILE GO_FILE
import { access, writeFile } from "node:fs/promises";
import { launchChromium, waitUntilSettled } from "./browser.mjs";

const [baseUrl, specimenId, readyFile, goFile] = process.argv.slice(2);
const browser = await launchChromium();
const result = { console: [], gone: 0 };
try {
  const page = await browser.newPage({ viewport: { width: 960, height: 720 } });
  page.on("console", (message) => { if (["warning", "error"].includes(message.type())) result.console.push(message.text()); });
  page.on("pageerror", (error) => result.console.push(String(error)));
  page.on("response", (response) => { if (response.status() === 410) result.gone += 1; });
  await page.goto(`${baseUrl}/viewer/?specimen=${specimenId}`);
  await waitUntilSettled(page, 300000);
  await writeFile(readyFile, "");
  for (let waited = 0; ; waited += 100) {
    if (await access(goFile).then(() => true, () => false)) break;
    if (waited > 120000) throw new Error("no go from the test within 120 s");
    await page.waitForTimeout(100);
  }
  const view = await page.locator("#view canvas").boundingBox();
  await page.mouse.move(view.x + view.width * 0.4, view.y + view.height * 0.4);
  for (let step = 0; step < 12; step++) {
    await page.mouse.wheel(0, -400);
    await page.waitForTimeout(50);
  }
  const position = () => page.evaluate(() => window.viewer.debug.camera.position.toArray());
  result.before = await position();
  await page.waitForFunction(() => window.viewer.status.reopened > 0, null, { timeout: 120000 });
  result.status = await waitUntilSettled(page, 300000);
  result.after = await position();
} finally {
  await browser.close();
}
result.console = result.console.filter((line) => !/status of 410|error code 410|Failed to load tile/.test(line) && line !== "Error: Failed to load model with error code 410");
console.log(JSON.stringify(result));
