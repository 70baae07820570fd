// What the browser tests share: Debian's Chromium through playwright-core (never a downloaded
// browser), how much of a WebGL canvas differs from its background, and driving the viewer.
import { chromium } from "playwright-core";

export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
    args: ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
  });
}

// What a WebGL canvas shows, against its `background` ([r, g, b]): `litFraction`, the share of
// pixels whose colour differs from it by more than 30; and over those pixels, `redMinusBlueSpread`,
// the 10th-to-90th percentile spread of (red - blue) / 255, which a height colour ramp from blue
// to yellow spreads and a single colour does not; `meanGrey`, their mean of (r + g + b) / 3.
export function canvasStats(page, selector, background) {
  return page.evaluate(([selector, background]) => {
    const pixels = window.__pixels(selector);
    const redMinusBlue = [];
    let grey = 0;
    for (let i = 0; i < pixels.length; i += 4) {
      const distance = Math.abs(pixels[i] - background[0]) + Math.abs(pixels[i + 1] - background[1]) + Math.abs(pixels[i + 2] - background[2]);
      if (distance > 30) {
        redMinusBlue.push((pixels[i] - pixels[i + 2]) / 255);
        grey += (pixels[i] + pixels[i + 1] + pixels[i + 2]) / 3;
      }
    }
    redMinusBlue.sort((a, b) => a - b);
    const at = (q) => redMinusBlue[Math.floor(q * (redMinusBlue.length - 1))];
    return {
      litFraction: redMinusBlue.length / (pixels.length / 4),
      redMinusBlueSpread: redMinusBlue.length ? at(0.9) - at(0.1) : 0,
      meanGrey: redMinusBlue.length ? grey / redMinusBlue.length : 0,
    };
  }, [selector, background]);
}

// How many pixels of a canvas lie within `tolerance` (sum of channel differences) of `colour`.
export function countColour(page, selector, colour, tolerance = 60) {
  return page.evaluate(([selector, colour, tolerance]) => {
    const pixels = window.__pixels(selector);
    let count = 0;
    for (let i = 0; i < pixels.length; i += 4) {
      if (Math.abs(pixels[i] - colour[0]) + Math.abs(pixels[i + 1] - colour[1]) + Math.abs(pixels[i + 2] - colour[2]) <= tolerance) count++;
    }
    return count;
  }, [selector, colour, tolerance]);
}

// The mean absolute difference of two pictures of a canvas (grey levels 0-255, over all pixels).
export async function canvasDifference(page, selector, change) {
  await page.evaluate((selector) => { window.__before = window.__pixels(selector); }, selector);
  await change();
  return page.evaluate((selector) => {
    const after = window.__pixels(selector);
    let sum = 0;
    for (let i = 0; i < after.length; i += 4) {
      sum += Math.abs((after[i] + after[i + 1] + after[i + 2]) - (window.__before[i] + window.__before[i + 1] + window.__before[i + 2])) / 3;
    }
    return sum / (after.length / 4);
  }, selector);
}

// Helpers the page needs: a canvas's pixels (RGBA) through a 2D copy.
export async function addPageHelpers(page) {
  await page.addInitScript(() => {
    window.__pixels = (selector) => {
      const canvas = document.querySelector(selector);
      const copy = document.createElement("canvas");
      copy.width = canvas.width;
      copy.height = canvas.height;
      const context = copy.getContext("2d");
      context.drawImage(canvas, 0, 0);
      return context.getImageData(0, 0, copy.width, copy.height).data;
    };
  });
}

// Waits until the viewer has loaded tiles and nothing is queued, downloading or parsing for a
// few checks in a row; returns its status, or throws after `timeoutMs`.
export async function waitUntilSettled(page, timeoutMs) {
  const started = Date.now();
  let quiet = 0;
  while (Date.now() - started < timeoutMs) {
    await page.waitForTimeout(250);
    const status = await page.evaluate(() => window.viewer?.status);
    quiet = status && status.settled ? quiet + 1 : 0;
    if (quiet >= 4) return status;
  }
  throw new Error(`the view did not settle within ${timeoutMs / 1000} s: ${JSON.stringify(await page.evaluate(() => window.viewer?.status))}`);
}

// Two animation frames: what was changed is on the canvas.
export function twoFrames(page) {
  return page.evaluate(() => new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(resolve))));
}

// Sets a control of the panel as a user would (its value, then an input event).
export async function setControl(page, selector, value) {
  await page.evaluate(([selector, value]) => {
    const input = document.querySelector(selector);
    if (input.type === "checkbox" || input.type === "radio") input.checked = value;
    else input.value = value;
    input.dispatchEvent(new Event("input", { bubbles: true }));
  }, [selector, value]);
  await twoFrames(page);
}

// Clicks points given as fractions of the 3D view's size.
export async function clickView(page, fractions) {
  const view = await page.locator("#view canvas").boundingBox();
  for (const [fx, fy] of fractions) await page.mouse.click(view.x + view.width * fx, view.y + view.height * fy);
}
