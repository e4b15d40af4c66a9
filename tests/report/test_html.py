"""The HTML report of a tiny evaluation run, opened from file:// in headless Chromium: every image
loads and the console holds no error; so does the 3D view the run wrote. The pages' style, read
from the file (`locretrieval.report.html`).

The browser tests need Debian's ``chromium`` and ``chromium-driver`` (``apt-get install chromium
chromium-driver``) and selenium (the ``dev`` extra); skipped, saying which is missing, without them.
"""

import re
import shutil
from pathlib import Path

import pytest
from helpers import evaluate, evaluate_config

try:
    from selenium import webdriver
except ImportError:
    webdriver = None

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
#: The mark of a test in headless Chromium.
in_chromium = pytest.mark.skipif(
    not (CHROMIUM and CHROMEDRIVER and webdriver),
    reason="headless Chromium is not installed: apt-get install chromium chromium-driver (Debian packages)"
    if webdriver
    else "selenium is not installed: pip install -e '.[dev]'",
)

#: The scene of tests/test_evaluation.py, the approximation paradigm only (seconds).
TINY_RUN = [
    "data.render.width=160", "data.render.height=120", "data.render.num_database=32", "data.render.num_queries=16",
    "data.render.texture_size=64", "data.render.length=20.0", "data.render.workers=1", "data.render.seed=3",
    "model.max_side=160", "model.step=4", "subsets.blur_width=160", "device=cpu",
    "paradigms.local_sfm.enabled=false", "paradigms.global_sfm.enabled=false", "output.ltvl=false",
]  # fmt: skip
#: JavaScript: once the page and its images are loaded, each image's source, whether it finished and its width.
IMAGES = """
const done = arguments[arguments.length - 1];
const images = Array.from(document.images);
Promise.all(images.map(i => i.complete ? null : new Promise(r => { i.onload = r; i.onerror = r; })))
  .then(() => done(images.map(i => [i.getAttribute("src"), i.complete, i.naturalWidth])));
"""


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("browser")
    output = root / "run"
    evaluate(evaluate_config(f"paths.root_dir={root}", "report.figure_formats=[png]", *TINY_RUN), output)
    return output


@pytest.fixture(scope="module")
def browser():
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--window-size=1400,1000",
    ):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=CHROMEDRIVER))
    driver.set_script_timeout(60)
    yield driver
    driver.quit()


def open_page(browser, page: Path) -> tuple[list, list]:
    """Load ``page`` from file://; returns ``[src, complete, naturalWidth]`` per image and the
    console's SEVERE entries."""
    browser.get_log("browser")  # drop what earlier pages logged
    browser.get(page.resolve().as_uri())
    images = browser.execute_async_script(IMAGES)
    return images, [entry for entry in browser.get_log("browser") if entry["level"] == "SEVERE"]


@in_chromium
@pytest.mark.slow
def test_report_html_shows_every_figure_and_gallery_image_without_console_errors(run, browser):
    images, errors = open_page(browser, run / "report.html")
    assert errors == []
    sources = [src for src, _, _ in images]
    assert any(src.startswith("figures/") for src in sources) and any(src.startswith("galleries/") for src in sources)
    assert (
        len([src for src in sources if src.startswith("galleries/")])
        == len(list((run / "galleries").rglob("*.jpg")))
        == 15
    )
    broken = [src for src, complete, width in images if not (complete and width > 0)]
    assert broken == []
    assert browser.title.startswith("locretrieval report")


@in_chromium
def test_the_3d_view_loads_without_console_errors(run, browser):
    page = run / "scene_3d.html"
    assert page.is_file()  # evaluate.py writes the 3D view (report.scene_view.enabled: true)
    assert 'href="scene_3d.html"' in (run / "report.html").read_text()
    images, errors = open_page(browser, page)
    assert errors == []
    assert all(complete and width > 0 for _, complete, width in images)


#: JavaScript: the globals a hostile dataset's handlers would set, and what the page shows of them.
PWNED = "return [window.__pwned === undefined ? null : window.__pwned, document.body.innerText];"
#: JavaScript: whether the plotly figure of the 3D view was drawn under its policy (its scripts ran).
PLOTTED = "const d = document.querySelector('.plotly-graph-div'); return !!(window.Plotly && d && d.data);"


@in_chromium
@pytest.mark.slow
def test_a_report_of_a_hostile_dataset_runs_no_script_and_shows_the_names(hostile_run, browser):
    from helpers import HOSTILE_IMAGE, HOSTILE_MODEL, HOSTILE_QUERY_FOLDER, HOSTILE_TAG

    images, errors = open_page(browser, hostile_run.run / "report.html")
    pwned, text = browser.execute_script(PWNED)
    assert pwned is None  # no onerror / onload handler of the dataset's names ran
    for name in (HOSTILE_QUERY_FOLDER, HOSTILE_TAG, HOSTILE_IMAGE, HOSTILE_MODEL):
        assert name in text  # shown as text where the report names it
    assert errors == []  # the policy refused nothing the report itself needs
    galleries = [src for src, _, _ in images if src.startswith("galleries/")]
    # every one of the 8 queries (fewer than the 10 worst and 5 random drawn), the hostile names' among them
    assert len(galleries) == 8 and all(complete and width > 0 for _, complete, width in images)


@in_chromium
def test_the_3d_view_of_a_hostile_dataset_draws_with_its_own_scripts_only(hostile_run, browser):
    _, errors = open_page(browser, hostile_run.run / "scene_3d.html")
    assert browser.execute_script(PLOTTED) is True
    assert browser.execute_script(PWNED)[0] is None
    assert errors == []


@in_chromium
def test_a_sweep_summary_and_its_optuna_figures_draw_with_their_own_scripts_only(tmp_path, browser):
    """summary.html and optuna.html of an Optuna study whose trial overrides hold markup: the
    markup shows as text, runs nothing, and Optuna's plotly figures draw under the page's policy."""
    import optuna
    from omegaconf import OmegaConf
    from training_runs import gap_run

    from locretrieval.report.training_summary import write_summary

    hostile = "model.name=<img src=x onerror=window.__pwned=1>"
    study = optuna.create_study(study_name="s", storage=f"sqlite:///{tmp_path / 'optuna.db'}", direction="maximize")
    for number, value in enumerate((10.0, 30.0, 20.0, 15.0, 25.0, 12.0, 28.0, 18.0, 22.0, 16.0)):  # importances from 10
        trial = study.ask()
        trial.suggest_float("module.optimizer.lr", 1e-5, 1e-3, log=True)
        study.tell(trial, value)
        run = gap_run(tmp_path, f"{number}_job", value, [("approximation/ewb/k3/5m_10deg", 5.0, value, 10.0, 40.0)])
        lr = f"module.optimizer.lr={trial.params['module.optimizer.lr']}"
        OmegaConf.save(OmegaConf.create([lr, hostile]), run / ".hydra" / "overrides.yaml")
        OmegaConf.save(OmegaConf.create({"hydra": {"job": {"num": number}}}), run / ".hydra" / "hydra.yaml")
    sweeper = {"_target_": "hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper", "study_name": "s"}
    sweeper["storage"] = f"sqlite:///{tmp_path / 'optuna.db'}"
    OmegaConf.save(
        OmegaConf.create({"hydra": {"job": {"name": "train"}, "sweeper": sweeper}}), tmp_path / "multirun.yaml"
    )
    write_summary([tmp_path], tmp_path)

    _, errors = open_page(browser, tmp_path / "summary.html")
    pwned, text = browser.execute_script(PWNED)
    assert pwned is None and hostile.removeprefix("model.name=") in text and errors == []
    assert "1 (best)" in text
    _, errors = open_page(browser, tmp_path / "optuna.html")
    drawn = "return Array.from(document.querySelectorAll('.plotly-graph-div')).map(d => !!(window.Plotly && d.data));"
    assert browser.execute_script(drawn) == [True, True]  # the optimization history and the importances
    assert errors == []


#: JavaScript: how far the page and each table reach beyond the window or their own box, in pixels.
WIDTHS = """
const page = document.documentElement.scrollWidth - window.innerWidth;
const body = document.body.getBoundingClientRect();
return [page, Array.from(document.querySelectorAll('table')).map(t => [
    t.scrollWidth - t.clientWidth,
    Math.max(...Array.from(t.querySelectorAll('th, td')).map(c => c.getBoundingClientRect().right)) - body.right])];
"""


@in_chromium
def test_a_sweep_summary_s_table_fits_the_page_its_long_cells_wrapped(tmp_path, browser):
    """The summary of two trials whose overrides and job folders are long unbroken words (as Hydra
    names a sweep's folders), at 1000 pixels: the page does not scroll sideways and the trial table
    shows every column, its cells wrapped, nothing cut or hidden behind a scroll."""
    from omegaconf import OmegaConf
    from training_runs import gap_run

    from locretrieval.training.summary import write_summary

    rows = [
        ("approximation/ewb/k3/5m_10deg", 10.0, 40.0, 20.0, 60.0),
        ("global_sfm/pnp/k5/0.25m_2deg", 50.0, 55.0, 50.0, 50.0),
        ("local_sfm/pnp/k10/0.25m_2deg", 10.0, 30.0, 20.0, 70.0),
    ]
    runs = []
    for number, probability in enumerate((0.489309171116382, 0.1023456789)):
        label = f"{number}_blur_probability={probability},brightness=0.123456789012"
        run = gap_run(tmp_path / "sweep", label, 40.0 - number, rows)
        overrides = [f"data.augmentation.blur_probability={probability}", "data.augmentation.brightness=0.12"]
        OmegaConf.save(OmegaConf.create(overrides), run / ".hydra" / "overrides.yaml")
        runs.append(run)
    write_summary(runs, tmp_path / "summary")
    browser.set_window_size(1000, 1000)
    try:
        _, errors = open_page(browser, tmp_path / "summary" / "summary.html")
        page, tables = browser.execute_script(WIDTHS)
    finally:
        browser.set_window_size(1400, 1000)
    assert errors == [] and len(tables) == 1
    assert page <= 0  # nothing wider than the window
    ((hidden, beyond),) = tables
    assert hidden <= 0 and beyond <= 0  # every column inside the table's box and the page's


def test_a_report_page_wraps_long_words_and_scrolls_a_wide_table_inside_itself(tmp_path):
    """The page's style (measured in Chromium by this file's browser tests): text breaks
    anywhere it must (a Hydra job folder is one long word), a table is its own scrolling box."""
    from locretrieval.report.html import write_html

    page = tmp_path / "summary.md"
    page.write_text("# s\n\n| trial | gap |\n| --- | --- |\n| 0_blur_probability=0.489309171116382,b=1 | 1 |\n")
    style = re.search(r"<style>(.*?)</style>", write_html(page).read_text(), re.DOTALL).group(1)
    rules = {
        selector.strip(): {
            item.split(":")[0].strip(): item.split(":", 1)[1].strip() for item in body.split(";") if ":" in item
        }
        for selector, body in re.findall(r"([^{}]+)\{([^}]*)\}", style)
    }
    assert rules["body"]["overflow-wrap"] == "anywhere"
    assert rules["table"]["display"] == "block" and rules["table"]["overflow-x"] == "auto"
    assert rules["table"]["max-width"] == "100%"
