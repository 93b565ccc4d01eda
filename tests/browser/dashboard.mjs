// The dashboard as an operator uses it, in Debian's headless Chromium. Started by
// tests/dashboard.rs with RIGCAL_E2E (servers, keys, prepared jobs, artifact dir);
// prints START_WORKER when it wants the worker started. Exit code 0 = all checks passed.
import { chromium } from "playwright-core";
import assert from "node:assert/strict";
import fs from "node:fs";
import path from "node:path";
import { createRequire } from "node:module";

const AXE = createRequire(import.meta.url).resolve("axe-core/axe.min.js");

const cfg = JSON.parse(process.env.RIGCAL_E2E);
const shots = cfg.artifacts;
const log = (...a) => console.log(...a);
const problems = [];

async function apiJson(base, key, p) {
  const r = await fetch(base + p, { headers: { Authorization: `Bearer ${key}` } });
  assert.equal(r.status, 200, `${p}: HTTP ${r.status}`);
  return r.json();
}

async function apiText(base, key, p) {
  const r = await fetch(base + p, { headers: { Authorization: `Bearer ${key}` } });
  assert.equal(r.status, 200, `${p}: HTTP ${r.status}`);
  return r.text();
}

// Accessibility: axe-core's WCAG 2 A/AA rules (labels, names, contrast, roles) on what
// the page shows now; serious and critical findings fail the test.
async function accessible(page, what) {
  await page.addScriptTag({ path: AXE });
  const found = await page.evaluate(async () => {
    const r = await window.axe.run(document, { runOnly: ["wcag2a", "wcag2aa"] });
    return r.violations.map((v) => ({ id: v.id, impact: v.impact, help: v.help, nodes: v.nodes.slice(0, 3).map((n) => n.target.join(" ")) }));
  });
  const bad = found.filter((v) => v.impact === "serious" || v.impact === "critical");
  for (const v of found) log(`axe ${what}: ${v.impact} ${v.id}: ${v.help} at ${v.nodes.join(", ")}`);
  assert.equal(bad.length, 0, `${what}: ${bad.length} serious accessibility violation(s)`);
  log(`axe ${what}: no serious violation (${found.length} minor)`);
}

async function shot(page, name) {
  await page.screenshot({ path: path.join(shots, `${name}.png`), fullPage: true });
}

function watch(page) {
  page.on("pageerror", (e) => problems.push(`page error: ${e.message}`));
  page.on("console", (m) => {
    // Chromium logs every refused request; the 401s of the key checks are intended.
    if (m.type() === "error" && !/status of 401/.test(m.text())) problems.push(`console error: ${m.text()}`);
  });
  page.on("request", (r) => {
    const u = new URL(r.url());
    if (!["127.0.0.1", "localhost"].includes(u.hostname) && u.protocol.startsWith("http")) problems.push(`request off the service: ${r.url()}`);
  });
}

const browser = await chromium.launch({
  executablePath: cfg.chromium,
  args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync"],
});

try {
  // ---- 1. No key: the page asks for one and shows nothing of any tenant. ----
  // bypassCSP: only so that axe-core can be injected; the page itself runs under its CSP
// in the other contexts.
  const ctx = await browser.newContext({ acceptDownloads: true, bypassCSP: true, viewport: { width: 1280, height: 900 } });
  const page = await ctx.newPage();
  watch(page);
  await page.goto(cfg.base + "/");
  await page.getByLabel("API key").waitFor();
  assert.equal(await page.locator("table").count(), 0, "no table before a key is given");
  await page.getByLabel("API key").fill("rk_not-a-key");
  await page.getByRole("button", { name: "Sign in" }).click();
  await page.getByText("That key was not accepted").waitFor();
  await shot(page, "01-key-form");
  await accessible(page, "key form");
  // Keyboard only from here: type the key, Enter.
  await page.getByLabel("API key").fill(cfg.key);
  await page.keyboard.press("Enter");
  await page.locator("#jobs-body tr[data-job]").first().waitFor();
  // Focus moved to the page's content; Tab reaches the first filter.
  await page.keyboard.press("Tab");
  assert.equal(await page.evaluate(() => document.activeElement.id), "status", "Tab from the content lands on the status filter");
  assert.equal(await page.evaluate(() => sessionStorage.getItem("rigcal.api_key")), cfg.key, "key kept in sessionStorage");
  assert.match(await page.locator("#who").textContent(), /factory/);
  const queuedBefore = await page.locator('#jobs-body tr[data-job] [data-status="queued"]').count();
  assert.equal(queuedBefore, 3, "the three prepared jobs are queued");
  await page.evaluate(() => { window.__noReload = "still-here"; });

  // ---- 2. Upload a session archive through the form; its capture check shows before
  // any job; the job starts from there. ----
  await page.getByRole("link", { name: "Upload" }).click();
  await page.getByLabel("Session archive").waitFor();
  await accessible(page, "upload form");
  await page.getByLabel("Session archive").setInputFiles(cfg.upload);
  await page.getByRole("button", { name: "Upload", exact: true }).click();
  await page.locator('#capture-check[data-complete="true"]').waitFor({ timeout: 30000 });
  const sessionId = (await page.locator("#upload-status").textContent()).match(/Session ([0-9a-f-]{36})/)[1];
  const apiCheck = await apiJson(cfg.base, cfg.key, `/v1/sessions/${sessionId}/check`);
  assert.equal(await page.locator("#check-verdict").getAttribute("data-verdict"), apiCheck.verdict, "the page shows the API's capture check");
  assert.equal(await page.locator("#check-reasons li").count(), apiCheck.reasons.length);
  await accessible(page, "upload page with its capture check");
  await shot(page, "02-capture-check");
  await page.getByRole("button", { name: "Start calibration job" }).click();
  await page.waitForFunction(() => /^#\/jobs\/[0-9a-f-]{36}$/.test(location.hash), null, { timeout: 30000 });
  const jobId = (await page.evaluate(() => location.hash)).split("/")[2];
  log(`uploaded; job ${jobId}`);
  await page.locator("#job-progress [data-status=queued]").waitFor();

  // ---- 3. The jobs table goes queued → succeeded live, without a reload. ----
  await page.getByRole("link", { name: "Jobs", exact: true }).click();
  const row = page.locator(`tr[data-job="${jobId}"]`);
  await row.locator("[data-status=queued]").waitFor();
  await shot(page, "02-jobs-queued");
  // Record every status the row shows from now on.
  await page.evaluate((id) => {
    window.__seen = [];
    const note = () => {
      const b = document.querySelector(`tr[data-job="${id}"] [data-status]`);
      const s = b && b.dataset.status;
      if (s && window.__seen[window.__seen.length - 1] !== s) window.__seen.push(s);
    };
    note();
    new MutationObserver(note).observe(document.getElementById("jobs-body"), { subtree: true, childList: true, attributes: true });
  }, jobId);
  log("START_WORKER");
  const t0 = Date.now();
  await row.locator("[data-status=succeeded]").waitFor({ timeout: 240000 });
  log(`queued -> succeeded on the page in ${((Date.now() - t0) / 1000).toFixed(1)} s`);
  const seen = await page.evaluate(() => window.__seen);
  log(`statuses seen: ${seen.join(" -> ")}`);
  assert.equal(seen[0], "queued");
  assert.equal(seen[seen.length - 1], "succeeded");
  assert.equal(await page.evaluate(() => window.__noReload), "still-here", "the page was not reloaded");
  // The finished row carries RMS and the verdict.
  assert.match(await row.locator("td.num").nth(1).textContent(), /^\d+\.\d{3}$/);
  assert.equal(await row.locator("[data-acceptance]").count(), 1);
  await shot(page, "03-jobs-succeeded");
  await accessible(page, "jobs page");

  // ---- 4. The job page shows what the API returns. ----
  await row.getByRole("link").first().focus();
  await page.keyboard.press("Enter");
  await page.locator("#extrinsics").waitFor();
  const result = await apiJson(cfg.base, cfg.key, `/v1/jobs/${jobId}/result`);
  const cells = await page.locator("#extrinsics td[data-field]").evaluateAll((tds) =>
    tds.map((td) => ({ camera: td.dataset.camera, field: td.dataset.field, value: Number(td.dataset.value), text: td.textContent })));
  assert.equal(cells.length, result.extrinsics.length * 6);
  const fields = ["x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"];
  for (const c of cells) {
    const e = result.extrinsics.find((x) => x.camera === c.camera);
    const k = fields.indexOf(c.field);
    const truth = k < 3 ? e.translation[k] * 1000 : e.rpy_deg[k - 3];
    const shown = Number(c.text.trim().split(/\s/)[0]);
    const tol = k < 3 ? 0.05 : 0.0005;
    assert.ok(Math.abs(shown - truth) <= tol + 1e-9, `${c.camera} ${c.field}: page ${shown}, API ${truth}`);
    const sigma = k < 3 ? e.sigma_translation_m[k] : e.sigma_rotation_deg[k - 3];
    if (sigma === null) assert.match(c.text, /unobservable/);
    else {
      const s = Number(c.text.split("±")[1]);
      const want = k < 3 ? sigma * 1000 : sigma;
      assert.ok(Math.abs(s - want) <= (k < 3 ? 0.005 : 0.0005) + 1e-9, `${c.camera} ${c.field} σ: page ${s}, API ${want}`);
    }
  }
  log(`job page: ${cells.length} extrinsic values match the API`);
  for (const f of ["rig.svg", "residual-histogram.svg", "residuals-per-camera.svg", "residuals-per-frame.svg"]) {
    await page.locator(`[data-figure="${f}"] svg`).waitFor();
  }
  assert.ok(await page.getByText(/Stages \(/).isVisible());
  // Downloads: the file saved is the API's export.
  for (const format of ["kalibr", "urdf"]) {
    const [dl] = await Promise.all([page.waitForEvent("download"), page.locator(`button[data-format=${format}]`).click()]);
    const file = path.join(shots, dl.suggestedFilename());
    await dl.saveAs(file);
    const want = await apiText(cfg.base, cfg.key, `/v1/jobs/${jobId}/result?format=${format}`);
    assert.equal(fs.readFileSync(file, "utf8"), want, `${format} download equals the API export`);
    log(`downloaded ${dl.suggestedFilename()} (${want.length} bytes)`);
  }
  {
    const b = page.locator("button[data-format=camera_info]").first();
    const camera = await b.getAttribute("data-camera");
    const [dl] = await Promise.all([page.waitForEvent("download"), b.click()]);
    const file = path.join(shots, dl.suggestedFilename());
    await dl.saveAs(file);
    const want = await apiText(cfg.base, cfg.key, `/v1/jobs/${jobId}/result?format=camera_info&camera=${encodeURIComponent(camera)}`);
    assert.equal(fs.readFileSync(file, "utf8"), want, "camera_info download equals the API export");
    assert.match(want, new RegExp(`camera_name: "${camera}"`));
  }
  await shot(page, "04-job");
  await accessible(page, "job page");

  // ---- 5. A singular drive: the unobservable direction and the recommendation. ----
  await page.evaluate((id) => { location.hash = `#/jobs/${id}`; }, cfg.planar_job);
  await page.locator("h1 code", { hasText: cfg.planar_job }).waitFor({ timeout: 120000 });
  await page.locator("#singularity.warn").waitFor({ timeout: 120000 });
  const planar = await apiJson(cfg.base, cfg.key, `/v1/jobs/${cfg.planar_job}/result`);
  assert.ok(planar.singularity.unobservable_directions.length >= 1, "car-planar has an unobservable direction");
  const unobs = await page.locator("#unobservable li").allTextContents();
  assert.equal(unobs.length, planar.singularity.unobservable_directions.length);
  assert.ok(unobs[0].includes(planar.singularity.unobservable_directions[0].description));
  const recs = await page.locator("#recommendations li").allTextContents();
  assert.deepEqual(recs, planar.singularity.recommendations);
  assert.ok(await page.locator("#extrinsics .unobservable").count() >= 1, "unobservable σ highlighted");
  log(`planar job: ${unobs.length} unobservable direction(s), ${recs.length} recommendation(s) shown`);
  await shot(page, "05-planar");
  await accessible(page, "singular job page");

  // ---- 6. A failed job says why and what is at fault. ----
  await page.evaluate((id) => { location.hash = `#/jobs/${id}`; }, cfg.failed_job);
  await page.locator("h1 code", { hasText: cfg.failed_job }).waitFor({ timeout: 120000 });
  await page.locator("#failure.bad").waitFor({ timeout: 120000 });
  const failedJob = await apiJson(cfg.base, cfg.key, `/v1/jobs/${cfg.failed_job}`);
  assert.equal(failedJob.status, "failed");
  const failText = await page.locator("#failure").textContent();
  assert.ok(failText.includes(failedJob.error.code), `failure box names ${failedJob.error.code}`);
  await shot(page, "06-failed");
  await accessible(page, "failed job page");

  // ---- 7. The vehicle: history and drift. ----
  await page.evaluate((v) => { location.hash = `#/vehicles/${v}`; }, cfg.vehicle);
  await page.getByRole("heading", { name: `Vehicle ${cfg.vehicle}` }).waitFor();
  await page.locator("figure svg").waitFor();
  const hist = await apiJson(cfg.base, cfg.key, `/v1/vehicles/${cfg.vehicle}/calibrations`);
  assert.equal(await page.locator("tbody tr").count(), hist.calibrations.length);
  assert.ok(hist.calibrations.length >= 2);
  const circles = await page.locator("figure svg circle").count();
  const changed = hist.calibrations.filter((c) => c.change_from_previous_accepted).reduce((a, c) => a + c.change_from_previous_accepted.length, 0);
  assert.equal(circles, 2 * changed, "one point per camera change, in both panels");
  await shot(page, "07-vehicle");
  await accessible(page, "vehicle page");
  assert.equal(await page.evaluate(() => window.__noReload), "still-here", "no reload anywhere");

  // ---- 7b. A vehicle model's fleet: the outlier found, every vehicle drawn. ----
  const fctx = await browser.newContext({ bypassCSP: true, viewport: { width: 1280, height: 900 } });
  await fctx.addInitScript((k) => sessionStorage.setItem("rigcal.api_key", k), cfg.fleet.key);
  const fp = await fctx.newPage();
  watch(fp);
  await fp.goto(cfg.fleet.base + "/#/jobs");
  await fp.getByRole("link", { name: "Fleet" }).click();
  await fp.getByRole("link", { name: cfg.fleet.model }).click();
  await fp.getByRole("heading", { name: `Fleet of ${cfg.fleet.model}` }).waitFor();
  await fp.locator("figure[data-camera] svg").first().waitFor();
  const fleetApi = await apiJson(cfg.fleet.base, cfg.fleet.key, `/v1/vehicle-models/${cfg.fleet.model}/fleet`);
  assert.equal(fleetApi.vehicles, cfg.fleet.vehicles);
  const flagged = await fp.locator("#outliers tbody tr").evaluateAll((rows) => rows.map((r) => r.dataset.vehicle));
  assert.deepEqual(flagged, [cfg.fleet.knocked], "the knocked vehicle and no other is an outlier");
  // One dot per vehicle on each of the six axes; the outlier's dots marked.
  const dots = await fp.locator("figure[data-camera] svg circle:not(:has(title))").count();
  assert.equal(dots, 6 * cfg.fleet.vehicles, "six strips of one dot per vehicle");
  assert.ok(await fp.locator("figure[data-camera] svg circle.outlier").count() >= 1, "the outlier's dots are marked");
  await shot(fp, "07b-fleet");
  await accessible(fp, "fleet page");
  // Its job fails the line against the nominal rig, and says which camera.
  await fp.locator(`#outliers a[href="#/jobs/${cfg.fleet.knocked_job}"]`).click();
  await fp.locator("section.nominal tr[data-camera=cam2][data-within=false]").waitFor();
  assert.match(await fp.locator("section.nominal").textContent(), /rotation [12]\.\d{3} deg from nominal exceeds 0\.5/);
  assert.equal(await fp.locator("[data-acceptance]").first().getAttribute("data-acceptance"), "fail");
  // Exports in the vehicle frame: the download is the API's export with frame=vehicle.
  await fp.getByLabel("Export frame").selectOption("vehicle");
  const [vdl] = await Promise.all([fp.waitForEvent("download"), fp.locator("button[data-format=urdf]").click()]);
  const vfile = path.join(shots, vdl.suggestedFilename());
  await vdl.saveAs(vfile);
  const vwant = await apiText(cfg.fleet.base, cfg.fleet.key, `/v1/jobs/${cfg.fleet.knocked_job}/result?format=urdf&frame=vehicle`);
  assert.equal(fs.readFileSync(vfile, "utf8"), vwant, "vehicle-frame URDF download equals the API export");
  assert.match(vwant, /<parent link="base_link"\/>/);
  assert.match(vdl.suggestedFilename(), /-urdf-vehicle\.urdf$/);
  await shot(fp, "07c-nominal");
  await accessible(fp, "job page against the nominal rig");
  await fctx.close();

  // ---- 8. A tablet: no sideways scrolling of the page itself. ----
  const tablet = await browser.newContext({ viewport: { width: 768, height: 1024 } });
  // A key given earlier in this tab's session.
  await tablet.addInitScript((k) => sessionStorage.setItem("rigcal.api_key", k), cfg.key);
  const tp = await tablet.newPage();
  watch(tp);
  await tp.goto(cfg.base + `/#/jobs/${jobId}`);
  await tp.locator("#extrinsics").waitFor();
  const overflow = await tp.evaluate(() => document.documentElement.scrollWidth - window.innerWidth);
  assert.ok(overflow <= 0, `page wider than a tablet by ${overflow}px`);
  await shot(tp, "08-tablet-job");
  await tablet.close();

  // ---- 9. 10 000 jobs: first render, paging, filtering. ----
  const bctx = await browser.newContext({ viewport: { width: 1280, height: 900 } });
  await bctx.addInitScript((k) => sessionStorage.setItem("rigcal.api_key", k), cfg.big.key);
  const bp = await bctx.newPage();
  watch(bp);
  const times = [];
  for (let i = 0; i < 5; i++) {
    const t = Date.now();
    await bp.goto(cfg.big.base + `/?run=${i}#/jobs`);
    await bp.locator("#jobs-body tr[data-job]").first().waitFor();
    times.push(Date.now() - t);
  }
  times.sort((a, b) => a - b);
  const summary = await bp.locator("#jobs-summary").textContent();
  assert.match(summary, new RegExp(`of ${cfg.big.jobs} `));
  assert.equal(await bp.locator("#jobs-body tr[data-job]").count(), 25);
  const renderMs = await bp.evaluate(() => document.body.dataset.jobsRenderMs);
  log(`10000 jobs: time to first rendered row ${times[2]} ms median of 5 (min ${times[0]}, max ${times[4]}); list fetch + render ${renderMs} ms`);
  await shot(bp, "09-jobs-10000");
  let t = Date.now();
  await bp.getByRole("link", { name: "Older →" }).click();
  await bp.locator("#jobs-summary", { hasText: /Jobs 26–50 of 10000/ }).waitFor();
  log(`10000 jobs: next page in ${Date.now() - t} ms`);
  t = Date.now();
  await bp.evaluate(() => { location.hash = "#/jobs?page=399"; });
  await bp.locator("#jobs-summary", { hasText: /Jobs 9976–10000 of 10000/ }).waitFor();
  log(`10000 jobs: last page in ${Date.now() - t} ms`);
  t = Date.now();
  await bp.getByLabel("Status").selectOption("failed");
  await bp.getByRole("button", { name: "Apply" }).click();
  await bp.locator("#jobs-summary", { hasText: new RegExp(`of ${cfg.big.failed} `) }).waitFor();
  log(`10000 jobs: filter status=failed (${cfg.big.failed}) in ${Date.now() - t} ms`);
  const statuses = await bp.locator("#jobs-body [data-status]").evaluateAll((b) => b.map((x) => x.dataset.status));
  assert.ok(statuses.length === 25 && statuses.every((s) => s === "failed"));
  await bp.getByLabel("Vehicle").fill("fleet-5");
  await bp.getByRole("button", { name: "Apply" }).click();
  await bp.waitForFunction(() => /vehicle=fleet-5/.test(location.hash));
  // The rows of the previous filter stay until the new page has loaded: wait for rows
  // that answer the vehicle query, not merely for rows.
  await bp.locator('#jobs-body[data-query*="vehicle_id=fleet-5"] tr[data-job]').first().waitFor();
  const vehicles = await bp.locator("#jobs-body tr[data-job] td:nth-child(2)").allTextContents();
  assert.ok(vehicles.length > 0 && vehicles.every((v) => v === "fleet-5"), `vehicle filter: ${vehicles}`);
  await bctx.close();

  if (problems.length) throw new Error(problems.join("\n"));
  log("all dashboard checks passed");
} catch (e) {
  console.error(e);
  process.exitCode = 1;
} finally {
  await browser.close();
}
