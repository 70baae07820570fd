// What the browser tests share: Debian's Chromium through playwright-core (never a downloaded
// browser), and how much of a WebGL canvas differs from its background.
import { chromium } from "playwright-core";

export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM ?? "/usr/bin/chromium",
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
  });
}

// Share of the canvas's pixels whose colour differs from `background` ([r, g, b]) by more than 30.
export function litFraction(page, selector, background) {
  return page.evaluate(([selector, background]) => {
    const canvas = document.querySelector(selector);
    const copy = document.createElement("canvas");
    copy.width = canvas.width; copy.height = canvas.height;
    const context = copy.getContext("2d");
    context.drawImage(canvas, 0, 0);
    const pixels = context.getImageData(0, 0, copy.width, copy.height).data;
    let lit = 0;
    for (let i = 0; i < pixels.length; i += 4) {
      const distance = Math.abs(pixels[i] - background[0]) + Math.abs(pixels[i + 1] - background[1]) + Math.abs(pixels[i + 2] - background[2]);
      if (distance > 30) lit++;
    }
    return lit / (pixels.length / 4);
  }, [selector, background]);
}
