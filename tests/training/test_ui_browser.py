"""A reviewer's first look, in a real browser: `bronchopose ui` on a tiny finished sweep, driven by headless
Chromium (Debian's `chromium`, installed by .ci/run) through Playwright (the PyPI package; no browser download).

What is asserted is what the page shows or fetches: the printed link lands on the runs table with the headline
metric as a column, its values visible without a click and sorted best first; so does the UI's bare address in a
fresh browser profile, and MLflow's own navigation from there (Experiments, then the experiment) opens the runs
table in the model-training view, its Views menu listing the headline view; a run's training-loss chart has a
point per logged step. Screenshots of a failing page go to ``$BRONCHOPOSE_TEST_ARTIFACTS`` (default: the test's
tmp folder, printed); ``BRONCHOPOSE_DOCS_SCREENSHOTS=1`` refreshes the screenshots in docs/img.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from bronchocli.config import load_config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import TAG_PARENT
from bronchocli.runs.views import (
    CURVE_METRICS,
    CURVES_SECTION,
    HEADLINE,
    HEADLINE_SCATTERS,
    HEADLINE_SECTION,
    ACC_RATIO,
    TAG_VERDICT,
    VIEW_KEY,
    VIEW_METRICS,
    VIEW_NAME,
)
from bronchocli.sweep import SweepStore, Worker
from bronchocli.sweep.plan import add_cells
from bronchocli.training.run import run_cell

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]
MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
STEPS = 30  # with runs.log_every 1: a training-loss point per step
DOCS_IMG = Path(__file__).resolve().parents[2] / "docs" / "img"

playwright = pytest.importorskip("playwright.sync_api", reason="the browser test needs `pip install playwright`")
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (.ci/run does)")]

CONFIG = f"""\
name: browse
dataset: {{root: tiny}}
splits: {{train: 1, val: 1, test: 1, cross_subject_val: 1}}
data: {{window: 3, image_size: 32}}
train: {{batch_size: 6, steps: {STEPS}, val_every: {STEPS}, bn_recalibrate: 2, threads: 1}}
runs: {{model_artifact: none, log_every: 1, system_metrics_interval_s: 1}}
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sweep(tiny_project):
    """A finished two-cell sweep (two seeds) of the tiny project: (config, client, experiment id, cell runs)."""
    path = tiny_project / "browse.yaml"
    path.write_text(CONFIG)
    cfg = load_config(path)
    client = client_for(cfg)
    exp = experiment_id(client, cfg)
    store = SweepStore(cfg.paths.storage_url)
    store.ensure_schema()
    cells = [cfg.cell(arch="baseline", rot_loss="mse", population="personalized", seed=s) for s in (0, 1)]
    add_cells(cfg, store, cells)
    assert Worker(cfg, cells, store, run_cell).run() == 0
    runs = [client.get_run(r.run_id) for r in store.rows(cfg.name)]
    assert all(r.info.status == "FINISHED" for r in runs)
    return path, client, exp, runs


@pytest.fixture(scope="module")
def ui(sweep):
    """`bronchopose ui` on the sweep's store: (base URL, the printed runs-table link)."""
    path, *_ = sweep
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-c", MAIN, "ui", "-c", str(path), "--port", str(port)],
                            cwd=path.parent, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env={**os.environ, "COLUMNS": "400"})
    base = f"http://127.0.0.1:{port}"
    try:
        link = None
        for line in proc.stdout:  # the link is printed before the server starts
            if "runs of experiment" in line:
                link = line.split(": ", 1)[1].strip()
                break
        assert link and link.startswith(base), link
        deadline = time.monotonic() + 900  # a busy 2-core machine starts MLflow's server in minutes
        while True:
            try:
                with urllib.request.urlopen(f"{base}/health", timeout=2) as response:
                    if response.status == 200:
                        break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"the UI did not come up (exit {proc.poll()})")
                time.sleep(0.5)
        yield base, link
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=60)


@pytest.fixture(scope="module")
def browser():
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, request, tmp_path):
    """A fresh page (no saved UI state); its screenshot is kept when the test fails."""
    context = browser.new_context(viewport={"width": 1600, "height": 1000})
    pg = context.new_page()
    pg.set_default_timeout(240_000)  # a busy 2-core machine serves pages slowly (a Zen 3 under the suite: > 120 s)
    failed_before = request.session.testsfailed
    yield pg
    if request.session.testsfailed > failed_before:  # this test's call failed
        folder = Path(os.environ.get("BRONCHOPOSE_TEST_ARTIFACTS") or tmp_path)
        folder.mkdir(parents=True, exist_ok=True)
        shot = folder / f"{request.node.name}.png"
        with contextlib.suppress(Exception):
            pg.screenshot(path=str(shot), full_page=True)
            print(f"screenshot of the failing page: {shot}")
    context.close()


def _docs_screenshot(page, name: str) -> None:
    if os.environ.get("BRONCHOPOSE_DOCS_SCREENSHOTS") == "1":
        page.screenshot(path=str(DOCS_IMG / name))


# -- helpers (also for later assertions on the sweep's parent run) -----------------------------------------------


def open_run_artifacts(page, base: str, experiment: str, run_id: str) -> list[str]:
    """Open a run's Artifacts tab and return the paths its tree lists (folders opened, as a reviewer would)."""
    listed: dict[str, bool] = {}

    def seen(response) -> None:
        if "/artifacts/list" in response.url and response.ok:
            for f in response.json().get("files", []):
                listed[f["path"]] = f["is_dir"]

    page.on("response", seen)
    try:
        with page.expect_response(lambda r: "/artifacts/list" in r.url):
            page.goto(f"{base}/#/experiments/{experiment}/runs/{run_id}/artifacts")
        opened: set[str] = set()
        while folders := [p for p, is_dir in listed.items() if is_dir and p not in opened]:
            for folder in folders:
                opened.add(folder)
                node = page.get_by_test_id("artifact-tree-node").filter(has_text=folder.rsplit("/", 1)[-1]).first
                with page.expect_response(lambda r: "/artifacts/list" in r.url and "path=" in r.url):
                    node.click()
        names = page.get_by_test_id("artifact-tree-node").all_inner_texts()
    finally:
        page.remove_listener("response", seen)
    return sorted(p for p in listed if p.rsplit("/", 1)[-1] in {n.strip() for n in names})


def open_parent_run_artifacts(page, base: str, client, experiment: str, run) -> list[str]:
    """Open the sweep's parent run (the parent of the cell run ``run``) and list its artifacts."""
    return open_run_artifacts(page, base, experiment, run.data.tags[TAG_PARENT])


# -- the tests ---------------------------------------------------------------------------------------------------


def significant_digits(text: str) -> int:
    """The significant digits of a number as written ("0.8230" -> 4, "-0.00151" -> 3, "12350" -> 4)."""
    mantissa = re.split(r"[eE]", text.strip().lstrip("+-"))[0]
    digits = mantissa.replace(".", "").lstrip("0")
    return len(digits.rstrip("0") if "." not in mantissa else digits) or 1


def _columns(page, columns: list[str], n: int) -> dict[str, list[str]]:
    """The table's cells of ``columns`` (col-ids) row by row (row-index order), read in one evaluation in the page
    once ``n`` rows show every one of them: the table re-renders as the page settles or a view is chosen, so rows
    counted in one call may be gone by the next (a CI run read an empty table that way)."""
    shown = page.wait_for_function(
        """([columns, n]) => {
            const rows = [...document.querySelectorAll('.ag-center-cols-container .ag-row')]
                .map(r => [Number(r.getAttribute('row-index')),
                           columns.map(c => ((r.querySelector(`[col-id="${c}"]`) || {}).innerText || '').trim())]);
            if (rows.length < n || rows.some(([, cells]) => cells.some(text => !text))) return null;
            rows.sort((a, b) => a[0] - b[0]);
            return Object.fromEntries(columns.map((c, j) => [c, rows.map(([, cells]) => cells[j])]));
        }""",
        arg=[columns, n])
    return shown.json_value()


def _metric_cells(page, n: int) -> dict[str, list[str]]:
    """The headline view's metric columns as the table shows them, row by row (row-index order)."""
    cells = _columns(page, [f"metrics.`{m}`" for m in VIEW_METRICS], n)
    return {m: cells[f"metrics.`{m}`"] for m in VIEW_METRICS}


def test_the_link_lands_on_the_runs_sorted_by_the_headline_best_first(ui, sweep, page):
    """One row per run (issue 48.5: not grouped), best first, the headline figures with at most 4 significant
    digits, as logged."""
    base, link = ui
    _, _, _, runs = sweep
    page.goto(link)
    column = f"metrics.`{HEADLINE}`"
    header = page.locator(f'.ag-header-cell[col-id="{column}"]')
    header.wait_for(state="visible")
    box = header.bounding_box()
    assert box is not None and box["x"] + box["width"] / 2 < page.viewport_size["width"]  # on screen, no scrolling
    assert HEADLINE in header.inner_text()
    shown = _metric_cells(page, len(runs))
    values = sorted(r.data.metrics[HEADLINE] for r in runs)
    assert [float(v) for v in shown[HEADLINE]] == values  # the cells only: no parent row; best (lowest) first
    every = [v for column in shown.values() for v in column]
    assert len(every) == len(VIEW_METRICS) * len(runs) and all(every), shown
    assert max(significant_digits(v) for v in every) <= 4, shown  # rounded (issue 48.5): MLflow shows them whole
    best = min(runs, key=lambda r: r.data.metrics[HEADLINE])
    first_name = page.locator('.ag-row[row-index="0"] [col-id="attributes.`Run Name`"] a').inner_text().strip()
    assert first_name == best.info.run_name and re.fullmatch(r"Baseline MSE\+MSE · s\d · pers · world", first_name)
    assert not page.locator('.ag-header-cell[col-id*="loss"]').count()  # no loss of mixed scale among the columns
    _docs_screenshot(page, "mlflow-runs-table.png")


def test_the_bare_address_lands_on_the_accumulated_column_and_the_seed_of_every_row(ui, sweep, page):
    """Issue 57.1: from the UI's bare address, the landing view shows the accumulated position ratio (the paper's
    headline) beside the per-pair one and the † verdict column, all on screen, and every row's run name shows its
    model, loss and seed inside the name column (not cut off)."""
    base, _ = ui
    _, _, _, runs = sweep
    page.goto(f"{base}/")
    acc, verdict = f"metrics.`{ACC_RATIO}`", f"tags.`{TAG_VERDICT}`"
    for column in (acc, f"metrics.`{HEADLINE}`", verdict):
        header = page.locator(f'.ag-header-cell[col-id="{column}"]')
        header.wait_for(state="visible")
        box = header.bounding_box()
        assert box is not None and box["x"] + box["width"] <= page.viewport_size["width"], (column, box)
    shown = _columns(page, [acc], len(runs))[acc]  # row-index order
    by_name = {r.info.run_name: r for r in runs}
    names = [page.locator(f'.ag-row[row-index="{i}"] [col-id="attributes.`Run Name`"] a').inner_text().strip()
             for i in range(len(runs))]  # the name column is pinned: its cells are outside the centre container
    for value, name in zip(shown, names):
        assert float(value) == by_name[name].data.metrics[ACC_RATIO]
    judged = page.evaluate(f"() => [...document.querySelectorAll('.ag-center-cols-container .ag-row')].map(r => "
                           f"((r.querySelector('[col-id=\"{verdict}\"]') || {{}}).innerText || '').trim())")
    assert sorted(judged) == sorted(r.data.tags[TAG_VERDICT] for r in runs), judged
    assert all(re.fullmatch(r"pair [✓†] · acc [✓†]", j) for j in judged), judged
    # the model, the loss and the seed lie inside the visible name column, in every row
    inside = page.evaluate("""() => [...document.querySelectorAll('.ag-cell[col-id="attributes.`Run Name`"]')]
      .filter(cell => cell.querySelector('a')).map(cell => {
        const link = cell.querySelector('a'), text = link.innerText, m = text.match(/^.*? · s\\d+/);
        const walker = document.createTreeWalker(link, NodeFilter.SHOW_TEXT);
        let node, left = m[0].length, range = document.createRange();
        while ((node = walker.nextNode()) && left > node.length) left -= node.length;
        range.setStart(link, 0); range.setEnd(node, left);
        return [m[0], range.getBoundingClientRect().right <= cell.getBoundingClientRect().right];
    })""")
    assert len(inside) == len(runs) and all(ok for _, ok in inside), inside
    assert sorted(seed for seed, _ in inside) == sorted(re.match(r"^.*? · s\d+", n)[0] for n in by_name)


def _headline_rows(page, runs) -> list[float]:
    """The headline column's values as the table shows them, row by row."""
    column = f"metrics.`{HEADLINE}`"
    page.locator(f'.ag-header-cell[col-id="{column}"]').wait_for(state="visible")
    return [float(v) for v in _columns(page, [column], len(runs))[column]]


def test_a_fresh_browser_at_the_uis_address_lands_on_the_headline_and_mlflows_navigation_stays_there(
        ui, sweep, page):
    """Issues 36.5, 48.5, no shared link: a fresh browser profile opens the UI's address and lands on the runs
    table in the model-training view with the headline, best first; MLflow's own navigation (Experiments, then
    the experiment) opens the experiment's runs table in the model-training view on the headline view, not the
    GenAI overview nor MLflow's default table, and its Views menu lists the headline view by name."""
    base, _ = ui
    _, _, exp, runs = sweep
    page.goto(f"{base}/")
    values = sorted(r.data.metrics[HEADLINE] for r in runs)
    assert _headline_rows(page, runs) == values  # the headline, best first
    assert f"#/experiments/{exp}/runs?" in page.url and "workflowType=machine_learning" in page.url
    assert page.evaluate("() => localStorage.getItem('mlflow.workflowType_v1')") == '"machine_learning"'
    assert page.get_by_test_id("saved-views-trigger").inner_text().strip() == VIEW_NAME
    page.locator('a[href="#/experiments"]').first.click()  # MLflow's own links from here on
    page.get_by_test_id("experiment-list-item-link").filter(has_text="browse").first.click()
    page.wait_for_url(re.compile(rf".*#/experiments/{exp}/runs\?.*"))
    assert "workflowType=machine_learning" in page.url and "/overview" not in page.url
    assert _headline_rows(page, runs) == values  # the headline view: sorted by the headline, its columns
    page.get_by_test_id("saved-views-trigger").click()
    page.get_by_test_id(f"saved-views-item-{VIEW_KEY}").click()  # the headline view, listed by name
    assert _headline_rows(page, runs) == values


def test_an_address_copied_from_the_bar_lands_on_the_runs_table_in_model_training_mode(ui, sweep, page):
    """Issue 48.5: a fresh browser opening ``/?ui=bronchopose#/experiments`` (an address of the UI with a query
    and a fragment) is in the model-training mode, and the experiment it clicks opens on the headline view; the
    Assistant panel is closed."""
    base, _ = ui
    _, _, exp, runs = sweep
    page.goto(f"{base}/?ui=bronchopose#/experiments")
    page.get_by_test_id("experiment-list-item-link").filter(has_text="browse").first.click()
    page.wait_for_url(re.compile(rf".*#/experiments/{exp}/runs\?.*"))
    assert "workflowType=machine_learning" in page.url and "/overview" not in page.url
    assert _headline_rows(page, runs) == sorted(r.data.metrics[HEADLINE] for r in runs)
    assert page.evaluate("() => localStorage.getItem('mlflow.assistant.panelOpen_v1')") == "false"
    assert page.evaluate("() => localStorage.getItem('mlflow.assistant.fab.autoOpenedOnFirstLoad_v1')") == "true"
    button = page.get_by_role("button", name="New run").bounding_box()  # the table's right edge: no panel beside it
    assert button is not None and button["x"] + button["width"] > 0.9 * page.viewport_size["width"], button


def test_a_runs_page_opens_its_charts_on_the_training_curve_without_scrolling(ui, sweep, page):
    """Issue 48.5: from the runs table, a run, then "Model metrics": the first chart is the training loss, drawn
    (a point per logged step) inside the window, no scrolling or searching."""
    base, link = ui
    _, _, exp, runs = sweep
    page.goto(link)
    run = runs[0]
    page.locator('[col-id="attributes.`Run Name`"] a').filter(has_text=run.info.run_name).first.click()
    page.wait_for_url(re.compile(rf".*#/experiments/{exp}/runs/{run.info.run_id}.*"))
    page.get_by_role("tab", name="Model metrics").click()
    card = page.get_by_test_id("experiment-view-compare-runs-card").first
    card.wait_for(state="visible")
    assert card.inner_text().strip().splitlines()[0] == CURVE_METRICS[0]
    page.wait_for_function("() => [...document.querySelectorAll('.js-plotly-plot')].some(p => p.data && "
                           "p.data.some(t => (t.x || []).length >= 30))")
    box = card.bounding_box()
    assert box is not None and 0 <= box["y"] and box["y"] + box["height"] <= page.viewport_size["height"]
    points = card.evaluate("c => [...c.querySelectorAll('.js-plotly-plot')].flatMap(p => (p.data || [])"
                           ".map(t => (t.x || []).length))")
    assert max(points) >= STEPS  # the curve, in the first card
    assert page.get_by_text(CURVES_SECTION, exact=True).first.is_visible()
    _docs_screenshot(page, "mlflow-training-curve.png")


def test_the_views_charts_open_on_the_training_and_validation_curves(ui, sweep, page):
    """The link's Chart view (issues 36.5, 48.5): the training and validation curves are the first section, in
    their order, then the headline figures, a point per run; no metric renamed for it."""
    _, link = ui
    page.goto(link)
    page.locator("label", has=page.locator('input[name="runs-view-mode"][value="CHART"]')).first.click()
    curves = page.get_by_text(CURVES_SECTION, exact=True).first
    curves.wait_for(state="visible")
    page.wait_for_function("n => document.querySelectorAll('[data-testid=experiment-view-compare-runs-card]')"
                           ".length >= n", arg=len(CURVE_METRICS))
    cards = page.get_by_test_id("experiment-view-compare-runs-card").all_inner_texts()
    shown = [t.strip().splitlines()[0] for t in cards]
    assert shown[:len(CURVE_METRICS)] == list(CURVE_METRICS), shown  # in their order, before any other chart
    head = page.get_by_text(HEADLINE_SECTION, exact=True).first  # (scrolled far below, MLflow drops it)
    head.wait_for(state="attached")
    names = page.evaluate("() => [...document.querySelectorAll('div')].filter(e => e.children.length === 0 && "
                          "/ metrics$|^Training and validation curves$|^Headline /.test(e.textContent))"
                          ".map(e => e.textContent)")
    assert names[:2] == [CURVES_SECTION, HEADLINE_SECTION], names  # the curves first, any other section after
    head.scroll_into_view_if_needed()  # the headline figures: a point per run, on axes fitted to the points
    page.wait_for_function("n => [...document.querySelectorAll('.js-plotly-plot')].filter(p => (p.data || [])"
                           ".some(t => t.mode === 'markers' && (t.x || []).length === n)).length >= 2",
                           arg=len(sweep[3]))
    scatters = ("() => [...document.querySelectorAll('.js-plotly-plot')].map(p => [(p.data || [])"
                ".filter(t => t.mode === 'markers'), p._fullLayout]).filter(([t]) => t.length).map(([t, l]) => "
                "[t[0].x, t[0].y, l.xaxis.range, l.yaxis.range])")
    page.wait_for_function(f"() => ({scatters})().every(([xs, ys, xr, yr]) => Math.min(...xs) >= xr[0] && "
                           "Math.max(...xs) <= xr[1] && Math.min(...ys) >= yr[0] && Math.max(...ys) <= yr[1])")
    plots = page.evaluate(scatters)  # laid out: each axis spans its points
    assert len(plots) == len(HEADLINE_SCATTERS), plots
    for xs, ys, x_range, y_range in plots:  # each axis spans about its points: from 0 only where they straddle it
        for values, (low, high) in ((xs, x_range), (ys, y_range)):
            assert low <= min(values) <= max(values) <= high, (values, low, high)
            assert not (min(values) > 0 >= low or max(values) < 0 <= high), (values, low, high)


def test_a_runs_training_loss_chart_has_a_point_per_logged_step(ui, sweep, page):
    base, _ = ui
    _, _, exp, runs = sweep
    page.goto(f"{base}/#/experiments/{exp}/runs/{runs[0].info.run_id}/model-metrics")
    with page.expect_response(lambda r: "get-history" in r.url and "metric_key=train_loss" in r.url) as got:
        page.get_by_placeholder("Search metric charts").fill("train_loss")
    fetched = got.value.json()["metrics"]  # the REST answer the chart is drawn from
    assert len(fetched) >= 30 and sorted(m["step"] for m in fetched) == list(range(1, STEPS + 1))
    page.wait_for_function("() => [...document.querySelectorAll('.js-plotly-plot')].some(p => p.data && p.data.length)")
    points = page.eval_on_selector_all(".js-plotly-plot", "els => els.flatMap(e => (e.data || []).map(t => "
                                                          "(t.x || []).length))")
    assert max(points) >= 30  # what the chart draws


def test_a_runs_artifacts_are_listed_as_the_reviewer_sees_them(ui, sweep, page):
    base, _ = ui
    _, client, exp, runs = sweep
    files = open_run_artifacts(page, base, exp, runs[0].info.run_id)
    assert {"config.yaml", "predictions.csv", "trajectories.png"} <= set(files)
    assert runs[0].data.tags[TAG_PARENT] == runs[1].data.tags[TAG_PARENT]  # one sweep parent to open
    assert isinstance(open_parent_run_artifacts(page, base, client, exp, runs[0]), list)


def test_the_sweep_parent_shows_the_reports_tables(ui, sweep, page, tmp_path):
    """`report` logs its tables to the sweep's parent run: the reviewer finds them among the parent's artifacts."""
    base, _ = ui
    path, client, exp, runs = sweep
    done = subprocess.run([sys.executable, "-c", MAIN, "report", "-c", str(path), "--table", "personalized",
                           "--out", str(tmp_path / "report")], cwd=path.parent, capture_output=True, text=True,
                          timeout=900, env={**os.environ, "COLUMNS": "400"})
    assert done.returncode == 0, done.stdout + done.stderr
    written = sorted(p.name for p in (tmp_path / "report").glob("table*-personalized-*.md"))
    assert written, done.stdout
    files = open_parent_run_artifacts(page, base, client, exp, runs[0])
    assert {f"report/{name}" for name in written} <= set(files), files  # the paper's table, in the UI
