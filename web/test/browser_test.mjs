// The job page in a real browser (Debian's chromium, driven by playwright-core): a server started
// here on loopback with --http-listen; a finished job's page must show its mesh in the 3D view
// (pixels of the canvas that are not background), and the job list must follow a running job's
// progress. Writes screenshots into --out.
//
// node browser_test.mjs --lsqsurfd BIN --lsqsurf BIN --sample CLOUD.ply --chromium BIN
//                       --modules DIR (holding node_modules/playwright-core) --out DIR
import { spawn, execFileSync } from 'node:child_process';
import { createRequire } from 'node:module';
import { mkdtempSync, mkdirSync, rmSync, writeFileSync } from 'node:fs';
import { tmpdir } from 'node:os';
import path from 'node:path';
import readline from 'node:readline';

const args = {};
for (let i = 2; i < process.argv.length; i += 2) args[process.argv[i].replace(/^--/, '')] = process.argv[i + 1];
for (const name of ['lsqsurfd', 'lsqsurf', 'sample', 'chromium', 'modules', 'out']) {
  if (!args[name]) throw new Error(`--${name} is required`);
}
const { chromium } = createRequire(path.join(path.resolve(args.modules), 'node_modules', 'x.js'))('playwright-core');

function check(condition, what) {
  if (!condition) throw new Error(`failed: ${what}`);
  console.log(`ok: ${what}`);
}

// lsqsurfd on loopback; resolves with its gRPC address and page URL once both listen.
function startServer(dataDir) {
  const server = spawn(args.lsqsurfd, ['--listen', '127.0.0.1:0', '--http-listen', '127.0.0.1:0',
    '--data-dir', dataDir, '--workers', '2'], { stdio: ['ignore', 'pipe', 'inherit'] });
  const lines = readline.createInterface({ input: server.stdout });
  return new Promise((resolve, reject) => {
    const seen = {};
    server.on('exit', (code) => reject(new Error(`lsqsurfd exited (${code})`)));
    lines.on('line', (line) => {
      if (line.startsWith('listening on ')) seen.grpc = line.split(' ').pop();
      if (line.startsWith('http on ')) seen.http = line.split(' ').pop();
      if (seen.grpc && seen.http) resolve({ server, ...seen });
    });
  });
}

function cli(address, ...rest) {
  return execFileSync(args.lsqsurf, ['--server', address, '-q', ...rest], { encoding: 'utf8' }).trim();
}

// The canvas's luminance, pixel by pixel (it keeps its drawing buffer, so it can be read back).
function luminance() {
  const canvas = document.getElementById('canvas');
  const copy = document.createElement('canvas');
  copy.width = canvas.width;
  copy.height = canvas.height;
  const context = copy.getContext('2d');
  context.drawImage(canvas, 0, 0);
  const { data } = context.getImageData(0, 0, copy.width, copy.height);
  const out = [];
  for (let i = 0; i < data.length; i += 4) out.push(Math.round(0.3 * data[i] + 0.59 * data[i + 1] + 0.11 * data[i + 2]));
  return out;
}

// The share of pixels that are not the white background.
function foregroundShare(pixels) {
  return pixels.filter((v) => v < 235).length / pixels.length;
}

async function main() {
  mkdirSync(args.out, { recursive: true });
  const work = mkdtempSync(path.join(tmpdir(), 'lsqsurf-browser-'));
  const { server, grpc, http } = await startServer(path.join(work, 'data'));
  const browser = await chromium.launch({
    executablePath: args.chromium,
    // Software WebGL (SwiftShader), and none of chromium's own network traffic.
    args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
      '--disable-quic', '--no-first-run', '--disable-background-networking', '--disable-component-update',
      '--disable-sync'],
  });
  try {
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    const errors = [];
    page.on('pageerror', (error) => errors.push(error.message));
    page.on('console', (message) => { if (message.type() === 'error') errors.push(message.text()); });

    // A finished job: its mesh in 3D.
    const finished = cli(grpc, 'submit', args.sample, '--method', 'pu', '--job-preview');
    cli(grpc, 'watch', finished);
    await page.goto(`${http}/jobs/${finished}`);
    await page.waitForSelector('#canvas[data-ready]', { timeout: 60000 });
    check(await page.getAttribute('#canvas', 'data-ready') === 'mesh', 'the 3D view decoded the mesh');
    check(Number(await page.getAttribute('#canvas', 'data-vertices')) > 10000, 'the mesh has its vertices');
    const whole = await page.evaluate(luminance);
    const share = foregroundShare(whole);
    check(share > 0.05 && share < 0.9, `the canvas shows the mesh (${(100 * share).toFixed(1)} % of its pixels)`);
    check(await page.locator('#pictures img').count() === 1, 'the job preview is shown');
    await page.selectOption('#color-by', 'degree');
    check((await page.textContent('#viewer-note')).startsWith('degree:'), 'the mesh is coloured by degree');
    await page.screenshot({ path: path.join(args.out, 'job-page.png') });
    check(errors.length === 0, `no errors in the page (${errors.join('; ')})`);

    // A mesh delivered in parts (a PU job over a cloud sent in parts): the parts joined in 3D.
    const tiled = cli(grpc, 'submit', args.sample, '--method', 'pu', '--part-points', '10000',
      '--param', 'tile_points=10000');
    cli(grpc, 'watch', tiled);
    const status = cli(grpc, 'status', tiled);
    const statistic = (name) => Number((status.match(new RegExp(`\\b${name}=([0-9.e+-]+)`)) || [])[1]);
    check(statistic('mesh_parts') > 1, `the job delivered its mesh in ${statistic('mesh_parts')} parts`);
    await page.goto(`${http}/jobs/${tiled}`);
    await page.waitForSelector('#canvas[data-ready]', { timeout: 60000 });
    check(await page.getAttribute('#canvas', 'data-ready') === 'mesh', 'the parts were decoded');
    check(Number(await page.getAttribute('#canvas', 'data-triangles')) === statistic('triangles'),
      `the joined parts hold the job's ${statistic('triangles')} triangles`);
    const joined = await page.evaluate(luminance);
    const partsShare = foregroundShare(joined);
    check(partsShare > 0.05 && partsShare < 0.9, `the canvas shows the joined mesh (${(100 * partsShare).toFixed(1)} %)`);
    // The same cloud in one piece and in tiles: the same surface, so the same picture, but for
    // the tiles' own small differences (a face joined wrongly would draw a streak across it).
    const differing = joined.filter((v, i) => Math.abs(v - whole[i]) > 40).length / joined.length;
    check(joined.length === whole.length && differing < 0.01,
      `the joined mesh looks as the whole one does (${(100 * differing).toFixed(2)} % of pixels differ)`);
    await page.selectOption('#color-by', 'degree');
    check((await page.textContent('#viewer-note')).startsWith('degree:'), 'the joined mesh is coloured by degree');
    check(errors.length === 0, `no errors in the page (${errors.join('; ')})`);

    // A volume job's isosurfaces: two levels of a linear field on a 9³ grid, coloured by level.
    const values = new Float32Array(9 * 9 * 9);
    for (let k = 0; k < 9; k++) {
      for (let j = 0; j < 9; j++) {
        for (let i = 0; i < 9; i++) values[(k * 9 + j) * 9 + i] = (i + 2 * j - k) / 8;
      }
    }
    const raw = path.join(work, 'field.raw');
    writeFileSync(raw, Buffer.from(values.buffer));
    const volume = cli(grpc, 'volume', raw, '--raw', '9x9x9:float32:0.125', '--field', 'f', '--iso', '0.5', '--iso', '1');
    const volumeStatus = cli(grpc, 'status', volume);
    const volumeTriangles = Number((volumeStatus.match(/\btriangles=(\d+)/) || [])[1]);
    await page.goto(`${http}/jobs/${volume}`);
    await page.waitForSelector('#canvas[data-ready]', { timeout: 60000 });
    check(Number(await page.getAttribute('#canvas', 'data-triangles')) === volumeTriangles,
      `the volume job's isosurfaces are shown (${volumeTriangles} triangles)`);
    await page.selectOption('#color-by', 'iso');
    check((await page.textContent('#viewer-note')) === 'iso: 0.5 to 1', 'the isosurfaces are coloured by level');
    check(errors.length === 0, `no errors in the page (${errors.join('; ')})`);

    // A running job: the list follows its progress.
    const tracking = spawn(args.lsqsurf, ['--server', grpc, '-q', 'track', '--interface', 'sphere', '--field',
      'deformation', '--steps', '100000', '--stride', '100000', '-o', path.join(work, 'track')], { stdio: 'ignore' });
    await page.goto(`${http}/`);
    const row = page.locator('#jobs tbody tr.state-running');
    await row.first().waitFor({ timeout: 60000 });
    const first = await row.first().locator('td.progress').textContent();
    await page.waitForFunction(
      (before) => {
        const cell = document.querySelector('#jobs tbody tr.state-running td.progress');
        return cell && cell.textContent !== before;
      }, first, { timeout: 60000 });
    const later = await row.first().locator('td.progress').textContent();
    check(later !== first, `the list follows the running job (${first.trim()} → ${later.trim()})`);
    check(await page.locator('#jobs tbody tr').count() === 4, 'the list holds the four jobs');
    await page.screenshot({ path: path.join(args.out, 'job-list.png') });
    const running = await row.first().getAttribute('data-job');
    cli(grpc, 'cancel', running);
    await page.locator(`#jobs tbody tr.state-cancelled[data-job="${running}"]`).waitFor({ timeout: 30000 });
    check(true, 'the list shows the job cancelled');
    tracking.kill();
  } finally {
    await browser.close();
    server.kill('SIGTERM');
    await new Promise((resolve) => server.on('exit', resolve));
    rmSync(work, { recursive: true, force: true });
  }
}

main().catch((error) => {
  console.error(error);
  process.exit(1);
});
