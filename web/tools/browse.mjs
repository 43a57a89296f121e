// Drive the web player in a real Chromium (Debian's, through playwright-core; never a downloaded browser) for
// the tests and the benchmark: run a JSON plan of steps and print one line of JSON with what they gathered.
//
//   node tools/browse.mjs PLAN.json [CHROMIUM]
//
// PLAN: {"webgpu": bool, "viewport": [w, h], "touch": bool, "steps": [...]}; each step one of
//   {"goto": URL}                                   open a page (console errors and page errors are collected)
//   {"initScript": JS}                              run before every page's own scripts (e.g. remove an API)
//   {"click": SELECTOR} / {"press": KEY}            a click or a key press
//   {"select": SELECTOR, "value": V}                choose an option
//   {"wait": JS_EXPRESSION, "timeout": ms}          until the expression (evaluated in the page) is truthy
//   {"sleep": ms}
//   {"eval": JS_EXPRESSION, "as": NAME}             evaluate (awaited) and keep the JSON result under NAME
//   {"screenshot": PATH, "selector": SELECTOR?}     save a PNG
//   {"download": SELECTOR, "path": PATH, "as": NAME} click, save the file it downloads; keep its suggested name
//   {"touch": [[x, y], ...], "to": [[x, y], ...], "moves": N}  fingers down at the first points, moved in N steps
//                                                   to the second, lifted (CDP touch events; needs "touch": true)
//   {"throttle": {"kbps": N, "latencyMs": N}}       CDP Network.emulateNetworkConditions (null: off)
// Output: {"results": {...}, "console": [...], "errors": [...], "url": ...}. Exit 1 with one line on stderr when
// a step fails (the output line still comes first, with "failed").
import { readFileSync } from "node:fs";
import { chromium } from "playwright-core";

const [planFile, executablePath = "/usr/bin/chromium"] = process.argv.slice(2);
if (!planFile) {
  process.stderr.write("usage: node tools/browse.mjs PLAN.json [CHROMIUM]\n");
  process.exit(2);
}
const plan = JSON.parse(readFileSync(planFile, "utf8"));
const args = [
  "--no-sandbox",
  "--disable-quic",
  "--no-first-run",
  "--disable-background-networking",
  "--disable-component-update",
  "--disable-sync",
  "--disable-background-timer-throttling",
  "--disable-renderer-backgrounding",
  "--disable-backgrounding-occluded-windows",
];
if (plan.webgpu) {
  args.push(
    "--enable-unsafe-webgpu",
    "--enable-features=Vulkan",
    "--use-vulkan=swiftshader",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
  );
} else {
  args.push("--use-angle=swiftshader", "--enable-unsafe-swiftshader");
}
// Polls with page.evaluate (the DevTools protocol's evaluation, which the page's CSP does not block, unlike
// waitForFunction's string form): the player runs under its own CSP in every test.
async function waitFor(page, expression, timeout) {
  const until = Date.now() + timeout;
  for (;;) {
    if (await page.evaluate(`(async () => (${expression}))()`)) return;
    if (Date.now() > until) throw new Error(`timed out after ${timeout} ms waiting for ${expression}`);
    await page.waitForTimeout(100);
  }
}

const browser = await chromium.launch({ executablePath, args });
const out = { results: {}, console: [], errors: [] };
let failure = null;
try {
  const [w, h] = plan.viewport ?? [800, 600];
  const page = await browser.newPage({ viewport: { width: w, height: h }, hasTouch: Boolean(plan.touch) });
  page.on("console", (m) => out.console.push({ type: m.type(), text: m.text().slice(0, 500) }));
  page.on("pageerror", (e) => out.errors.push(String(e).slice(0, 500)));
  let cdp = null;
  for (const step of plan.steps) {
    if (step.goto) await page.goto(step.goto);
    else if (step.initScript) await page.addInitScript(step.initScript);
    else if (step.click) await page.click(step.click);
    else if (step.press) await page.keyboard.press(step.press);
    else if (step.select) await page.selectOption(step.select, step.value);
    else if (step.wait) await waitFor(page, step.wait, step.timeout ?? 30000);
    else if (step.sleep) await page.waitForTimeout(step.sleep);
    else if (step.eval) out.results[step.as ?? "value"] = await page.evaluate(`(async () => (${step.eval}))()`);
    else if (step.touch) {
      cdp ??= await page.context().newCDPSession(page);
      const moves = step.moves ?? 8;
      const at = (s) =>
        step.touch.map(([x, y], i) => {
          const [tx, ty] = step.to[i];
          return { x: x + ((tx - x) * s) / moves, y: y + ((ty - y) * s) / moves, id: i };
        });
      await cdp.send("Input.dispatchTouchEvent", { type: "touchStart", touchPoints: at(0) });
      for (let s = 1; s <= moves; s++) {
        await cdp.send("Input.dispatchTouchEvent", { type: "touchMove", touchPoints: at(s) });
        await page.waitForTimeout(16);
      }
      await cdp.send("Input.dispatchTouchEvent", { type: "touchEnd", touchPoints: [] });
    } else if (step.download) {
      const [download] = await Promise.all([page.waitForEvent("download"), page.click(step.download)]);
      await download.saveAs(step.path);
      out.results[step.as ?? "download"] = download.suggestedFilename();
    } else if (step.screenshot) {
      const target = step.selector ? page.locator(step.selector) : page;
      await target.screenshot({ path: step.screenshot });
    } else if ("throttle" in step) {
      cdp ??= await page.context().newCDPSession(page);
      await cdp.send("Network.enable");
      const t = step.throttle;
      await cdp.send(
        "Network.emulateNetworkConditions",
        t
          ? {
              offline: false,
              latency: t.latencyMs ?? 0,
              downloadThroughput: (t.kbps * 1000) / 8,
              uploadThroughput: -1,
            }
          : { offline: false, latency: 0, downloadThroughput: -1, uploadThroughput: -1 },
      );
    } else throw new Error(`unknown step ${JSON.stringify(step)}`);
  }
  out.url = page.url();
} catch (err) {
  failure = err instanceof Error ? err.message.split("\n")[0] : String(err);
  out.failed = failure;
} finally {
  await browser.close();
}
process.stdout.write(`${JSON.stringify(out)}\n`);
if (failure) {
  process.stderr.write(`browse: ${failure}\n`);
  process.exitCode = 1;
}
