"""End to end in a real headless browser: open the page, see the pictures, write two instructions,
edit one, and turn the file into a `test_unseen_human` split.

Needs Debian's chromium and chromium-driver and the selenium package (`make test` installs them);
skipped, saying so, where they are missing.
"""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

import pytest

from demo_factory.collect.pictures import PictureCache, picture_seed
from demo_factory.collect.server import CollectApp, CollectServer
from demo_factory.collect.store import InstructionFile
from demo_factory.generate import EpisodeRequest, run_requests
from demo_factory.instructions import load_human_instructions
from demo_factory.tasks import get_task

CHROMIUM, CHROMEDRIVER = "/usr/bin/chromium", "/usr/bin/chromedriver"
TASK = "push_buttons"

pytestmark = pytest.mark.slow


@pytest.fixture
def browser(tmp_path):
    webdriver = pytest.importorskip("selenium.webdriver", reason="the selenium package is not installed "
                                    "(`make test` installs it)")
    missing = [path for path in (CHROMIUM, CHROMEDRIVER) if not Path(path).exists()]
    if missing:
        pytest.skip(f"{', '.join(missing)} missing: install Debian's chromium and chromium-driver "
                    "(`make test` does, where apt-get can)")
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1280,1600", f"--user-data-dir={tmp_path / 'profile'}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=webdriver.ChromeService(executable_path=CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


@pytest.fixture
def server(tmp_path):
    task = get_task(TASK)
    instructions = InstructionFile(tmp_path / "human.jsonl", task)
    server = CollectServer(CollectApp(instructions, PictureCache(task, tmp_path / "pictures")), "127.0.0.1", 0)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server
    server.shutdown()
    server.server_close()


def wait_for(driver, condition, timeout=60):
    from selenium.webdriver.support.ui import WebDriverWait

    return WebDriverWait(driver, timeout).until(lambda d: condition(d))


def pictures_loaded(driver) -> bool:
    return driver.execute_script(
        "const imgs = [...document.querySelectorAll('#pictures img')];"
        "return imgs.length > 0 && imgs.every(i => i.complete && i.naturalWidth > 0);")


def scene_label(driver) -> str:
    return driver.find_element("id", "scene-label").text


def test_two_instructions_typed_in_the_browser_become_a_human_split(browser, server, tmp_path):
    from selenium.webdriver.common.by import By

    browser.get(server.url)
    wait_for(browser, lambda d: d.find_element(By.ID, "writer-input").is_displayed())
    browser.find_element(By.ID, "writer-input").send_keys("w07")
    browser.find_element(By.ID, "writer-start").click()
    wait_for(browser, pictures_loaded)
    assert len(browser.find_elements(By.CSS_SELECTOR, "#pictures img")) == 3
    sizes = browser.execute_script("return [...document.querySelectorAll('#pictures img')].map(i => i.naturalWidth)")
    assert sizes == [320, 320, 320]

    typed = ["Press the dark green button first, then the <b>blue</b> one & stop",
             "hit the yellow button once"]
    for text in typed:
        before = scene_label(browser)
        browser.find_element(By.ID, "instruction").send_keys(text)
        browser.find_element(By.ID, "submit").click()
        wait_for(browser, lambda d: d.find_element(By.ID, "message").text.startswith("Saved"))
        wait_for(browser, lambda d: scene_label(d) != before and pictures_loaded(d))

    # The last entry is shown back as text, markup and all, and can be edited.
    assert browser.find_element(By.ID, "last-text").text == typed[1]
    browser.find_element(By.ID, "edit").click()
    edit = browser.find_element(By.ID, "edit-text")
    edit.clear()
    edit.send_keys("hit the yellow <i>button</i> once")
    browser.find_element(By.ID, "edit-save").click()
    wait_for(browser, lambda d: d.find_element(By.ID, "last-text").text == "hit the yellow <i>button</i> once")
    assert not browser.find_elements(By.CSS_SELECTOR, "#last-text *, #message *")  # text, never elements
    progress = browser.find_element(By.ID, "progress-text").text
    assert "2 of 100 scenes" in progress and "You wrote 2" in progress

    # Skip moves on without writing anything.
    before = scene_label(browser)
    browser.find_element(By.ID, "skip").click()
    wait_for(browser, lambda d: scene_label(d) != before)

    out = Path(server.app.instructions.path)
    rows = load_human_instructions(out)
    assert [r.instruction for r in rows] == [typed[0], "hit the yellow <i>button</i> once"]
    assert {r.author for r in rows} == {"w07"}

    try:
        from demo_factory.convert.converter import ConvertOptions, convert
    except ImportError:
        return  # no converter in this checkout: the file validating is all that can be checked
    task = get_task(TASK)
    requests = [EpisodeRequest(TASK, "test", r.variation_id, picture_seed(task, task.variation(r.variation_id)))
                for r in rows]  # the very scenes the writer saw
    recordings = tmp_path / "recordings"
    assert all(outcome.kept for outcome in run_requests(requests, recordings))
    result = convert(ConvertOptions(inputs=[recordings], out=tmp_path / "dataset", repo_id="local/collect_test",
                                    human_instructions=out, progress=False), log=lambda _: None)
    human = {s.name: s for s in result.splits}["test_unseen_human"]
    assert human.episodes == 2 and human.variations == 2
    shutil.rmtree(tmp_path / "dataset")
