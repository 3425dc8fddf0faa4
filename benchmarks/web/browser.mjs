// Debian's headless Chromium (software WebGL) for the page checks (stock_check.mjs, site_check.mjs), and the
// one browser the suite's browser tests share.
//   openBrowser(width, height): {context, close}. With TERRALOD_BROWSER_WS set (the suite's session browser,
//   tests/conftest.py `browser`) it connects to that browser and opens a fresh context (no cache, cookies
//   or storage of another check), closed again by close(); without it (benchmarks, a check run by hand) it
//   launches a browser of its own, closed by close().
//   node browser.mjs: launch the shared browser, print its DevTools websocket URL on one line, and close it
//   when stdin ends (its parent exited or closed the pipe).
import puppeteer from "puppeteer-core";

const ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
  "--disable-background-networking", "--disable-component-update", "--disable-sync",
  "--disable-background-timer-throttling", "--disable-renderer-backgrounding", "--disable-backgrounding-occluded-windows"];

function launch(width, height) {
  return puppeteer.launch({
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    headless: "new",
    args: [...ARGS, `--window-size=${width},${height}`],
  });
}

export async function openBrowser(width, height) {
  const ws = process.env.TERRALOD_BROWSER_WS;
  if (ws) {
    const browser = await puppeteer.connect({ browserWSEndpoint: ws });
    const context = await browser.createBrowserContext();
    return { context, close: async () => { await context.close(); await browser.disconnect(); } };
  }
  const browser = await launch(width, height);
  return { context: browser.defaultBrowserContext(), close: () => browser.close() };
}

if (import.meta.url === `file://${process.argv[1]}`) {
  const browser = await launch(900, 600);
  console.log(browser.wsEndpoint());
  process.stdin.resume();
  process.stdin.on("end", async () => { await browser.close(); process.exit(0); });
  process.stdin.on("error", async () => { await browser.close(); process.exit(0); });
}
