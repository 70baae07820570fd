// A build submitted over HTTP, followed in the viewer's specimen list: the page is opened before
// the build is submitted (by the test, once READY_FILE exists) and the entry's state and progress
// bar are read every 100 ms until it reads "built". Prints one JSON line: the states seen in
// order (each once), the bar fractions seen, the console's warnings and errors.
// Usage: node build_progress.mjs BASE_URL SPECIMEN READY_FILE TIMEOUT_S
import { writeFile } from "node:fs/promises";
import { launchChromium } from "./browser.mjs";

const [baseUrl, specimenId, readyFile, timeoutS] = process.argv.slice(2);
const browser = await launchChromium();
const result = { states: [], fractions: [], console: [], thumbnailPx: 0 };
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  page.on("console", (message) => { if (["warning", "error"].includes(message.type())) result.console.push(message.text()); });
  page.on("pageerror", (error) => result.console.push(String(error)));
  await page.goto(`${baseUrl}/viewer/`);
  await page.waitForSelector("#specimens .specimen, #specimens .specimen-empty");
  await writeFile(readyFile, "");
  const deadline = Date.now() + 1000 * Number(timeoutS);
  while (Date.now() < deadline) {
    const entry = await page.evaluate((id) => {
      const item = document.querySelector(`#specimens .specimen[data-specimen="${id}"]`);
      if (!item) return null;
      const bar = item.querySelector(".specimen-progress");
      const picture = item.querySelector("img.thumbnail");
      return {
        state: item.querySelector(".specimen-state").textContent,
        fraction: bar ? bar.style.getPropertyValue("--fraction") : null,
        thumbnailPx: picture && picture.complete ? picture.naturalWidth : 0,
      };
    }, specimenId);
    if (entry) {
      const kind = entry.state.replace(/:.*/, "");
      if (result.states.at(-1) !== kind) result.states.push(kind);
      if (entry.fraction && result.fractions.at(-1) !== entry.fraction) result.fractions.push(entry.fraction);
      result.thumbnailPx = entry.thumbnailPx;
      if (kind === "built" && entry.thumbnailPx > 0) break;
    }
    await page.waitForTimeout(100);
  }
} finally {
  await browser.close();
}
console.log(JSON.stringify(result));
