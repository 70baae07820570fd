// What the browser tests share: Debian's Chromium through playwright-core (never a downloaded
// browser), and how much of a WebGL canvas differs from its background.
import { chromium } from "playwright-core";

export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
  });
}

// What a WebGL canvas shows, against its `background` ([r, g, b]): `litFraction`, the share of
// pixels whose colour differs from it by more than 30; and over those pixels, `redMinusBlueSpread`,
// the 10th-to-90th percentile spread of (red - blue) / 255, which a height colour ramp from blue
// to yellow spreads and a single colour does not.
export function canvasStats(page, selector, background) {
  return page.evaluate(([selector, background]) => {
    const canvas = document.querySelector(selector);
    const copy = document.createElement("canvas");
    copy.width = canvas.width; copy.height = canvas.height;
    const context = copy.getContext("2d");
    context.drawImage(canvas, 0, 0);
    const pixels = context.getImageData(0, 0, copy.width, copy.height).data;
    const redMinusBlue = [];
    for (let i = 0; i < pixels.length; i += 4) {
      const distance = Math.abs(pixels[i] - background[0]) + Math.abs(pixels[i + 1] - background[1]) + Math.abs(pixels[i + 2] - background[2]);
      if (distance > 30) redMinusBlue.push((pixels[i] - pixels[i + 2]) / 255);
    }
    redMinusBlue.sort((a, b) => a - b);
    const at = (q) => redMinusBlue[Math.floor(q * (redMinusBlue.length - 1))];
    return {
      litFraction: redMinusBlue.length / (pixels.length / 4),
      redMinusBlueSpread: redMinusBlue.length ? at(0.9) - at(0.1) : 0,
    };
  }, [selector, background]);
}
