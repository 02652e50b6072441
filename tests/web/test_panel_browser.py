"""The panel in a real browser: Debian's chromium, headless, driven through chromedriver by Selenium,
against a real daemon on the simulated rig. It loads, strokes arrive, a run started from the page
ends, runs queued from the page wait for the run going (reordered, another's cancelled as an
operator), a run's notes edited on the page are what `usmswitchctl runs` shows, the estop pressed
with the token latches FAULT in the daemon, and the page without the token is refused and shows no
control of the queue or the notes. The screenshots it takes are docs/panel.md's: written to docs/img/
when USMSWITCH_SCREENSHOTS=1 (to refresh the docs' images), else beside the test's own files, so
that `make test` leaves the tree as it found it."""

from __future__ import annotations

import datetime
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from daemonproc import daemon_args, spawn, stop, wait_serving

from usmswitch.client import Client
from usmswitch.protocol.sockets import web_token_path

ROOT = Path(__file__).resolve().parents[2]
DOCS_IMG = ROOT / "docs" / "img"
CHROMIUM = "/usr/bin/chromium"
CHROMEDRIVER = "/usr/bin/chromedriver"


def _require_browser() -> None:
    """Skip (fail under CI=true) without the browser; one line naming the package."""
    for path, package in ((CHROMIUM, "chromium"), (CHROMEDRIVER, "chromium-driver")):
        if not (os.access(path, os.X_OK) or shutil.which(Path(path).name)):
            why = f"{package} missing ({path}): apt-get install {package}"
            if os.environ.get("CI") == "true":
                pytest.fail(why, pytrace=False)
            pytest.skip(why)


@pytest.fixture(scope="module")
def shots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the screenshots go (module docstring)."""
    return DOCS_IMG if os.environ.get("USMSWITCH_SCREENSHOTS") == "1" else tmp_path_factory.mktemp("shots")


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    _require_browser()
    tmp = tmp_path_factory.mktemp("browser")
    sock = tmp / "run" / "d.sock"
    proc = spawn(daemon_args(tmp, "--web", "127.0.0.1:0", "--period", "15ms", "--rig", "lab-a", socket=sock))
    try:
        wait_serving(sock, proc)
        with Client(str(sock)) as c:
            url = c.status()["web_url"]
        yield {"sock": sock, "url": url, "token": web_token_path(sock).read_text().strip()}
    finally:
        stop(proc)


@pytest.fixture(scope="module")
def browser(rig: dict[str, Any]) -> Iterator[Any]:
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    opts = Options()
    opts.binary_location = shutil.which("chromium") or CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1400,1000", "--hide-scrollbars"):  # fmt: skip
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver") or CHROMEDRIVER), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


def wait_for(what: str, check: Callable[[], Any], timeout_s: float = 10.0) -> Any:
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException

    end = time.monotonic() + timeout_s
    while True:
        try:
            got = check()
        except (StaleElementReferenceException, NoSuchElementException):
            got = None  # the page redrew the element meanwhile, or has yet to draw it: look again
        if got:
            return got
        if time.monotonic() > end:
            raise AssertionError(f"not within {timeout_s:g} s: {what}")
        time.sleep(0.05)


def body(driver: Any, key: str) -> str:
    return str(driver.find_element("tag name", "body").get_attribute(f"data-{key}"))


def text(driver: Any, element_id: str) -> str:
    return str(driver.find_element("id", element_id).text)


def test_the_panel_loads_and_strokes_arrive(rig: dict[str, Any], browser: Any) -> None:
    browser.get(f"{rig['url']}?token={rig['token']}")
    wait_for("the control badge", lambda: body(browser, "control") == "yes")
    assert "token" not in browser.current_url  # taken off the address bar once read
    first = wait_for("strokes on the plot", lambda: int(body(browser, "strokes")))
    wait_for("more strokes", lambda: int(body(browser, "strokes")) >= first + 30)
    assert text(browser, "rig") == "lab-a" and text(browser, "driver") == "sim"
    assert text(browser, "state") == "cycling" and text(browser, "targets") == "12.000 ms / 12.000 ms"
    assert "us" in text(browser, "stats") or "ms" in text(browser, "stats")
    assert browser.find_element("id", "estop").is_displayed()
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors


def test_a_run_started_from_the_page_ends(rig: dict[str, Any], browser: Any) -> None:
    for element_id, value in (("run-count", "40"), ("run-period", "15"), ("run-target", "12.5")):
        box = browser.find_element("id", element_id)
        box.clear()
        box.send_keys(value)
    with Client(str(rig["sock"])) as c:
        before = c.runs(1)[-1]["run_id"]
        browser.find_element("id", "start").click()
        run = wait_for("the run", lambda: (r := c.runs(1)[-1])["run_id"] > before and r)
        assert run["settings"]["count"] == 40 and run["settings"]["owner"] == "panel"
        wait_for("the run's end", lambda: c.status()["state"] == "idle")
    row = f'#runs tr[data-run="{run["run_id"]}"]'
    wait_for("the ended run listed", lambda: "done" in browser.find_element("css selector", row).text)
    assert "run-" in browser.find_element("css selector", f"{row} a").text
    wait_for("the targets shown", lambda: text(browser, "targets") == "12.500 ms / 12.500 ms")
    # The next run, endless, for the tests after.
    browser.find_element("id", "run-count").clear()
    browser.find_element("id", "run-count").send_keys("0")
    browser.find_element("id", "run-target").clear()
    browser.find_element("id", "start").click()
    with Client(str(rig["sock"])) as c:
        wait_for("cycling again", lambda: c.status()["state"] == "cycling")


def test_a_clients_run_is_taken_over_only_when_confirmed(rig: dict[str, Any], browser: Any) -> None:
    """Issue 37, item 5: the page's Start sent take_over and ended another client's run unasked.
    Now the daemon's refusal names the run, the page asks, and only a yes ends that run."""
    browser.get(f"{rig['url']}?token={rig['token']}")
    wait_for("the control badge", lambda: body(browser, "control") == "yes")
    for element_id, value in (("run-count", "0"), ("run-period", "15"), ("run-target", "")):
        box = browser.find_element("id", element_id)
        box.clear()
        box.send_keys(value)
    question = browser.find_element("id", "confirm")
    with Client(str(rig["sock"])) as c:
        # Whatever runs (the page's run from the test before, or the start-up run) gives way to it.
        theirs = c.start_cycling("15ms", 0, take_over=True, owner="lab script")["run_id"]
        browser.find_element("id", "start").click()
        wait_for("the page asking", question.is_displayed)
        asked = text(browser, "confirm-text")
        assert f"run {theirs} (lab script, endless strokes" in asked and "Take it over?" in asked, asked
        browser.find_element("id", "confirm-no").click()
        wait_for("the question gone", lambda: not question.is_displayed())
        wait_for("the cancel said", lambda: "cancelled" in text(browser, "notice"))
        going = c.runs(1)[-1]
        assert going["run_id"] == theirs and going["end_reason"] is None and c.status()["state"] == "cycling"
        browser.find_element("id", "start").click()
        wait_for("the page asking again", question.is_displayed)
        browser.find_element("id", "confirm-yes").click()
        mine = wait_for("the page's run", lambda: (r := c.runs(1)[-1])["run_id"] > theirs and r)
        assert mine["settings"]["owner"] == "panel" and mine["settings"]["took_over_run"] == theirs
        (ended,) = [r for r in c.runs(3) if r["run_id"] == theirs]
        assert ended["end_reason"] == "taken over by panel"
        assert c.status()["state"] == "cycling"  # the page's endless run, for the tests after


BOB = "bob@elsewhere pid 1 (bob.py)"


def fill(driver: Any, **values: str) -> None:
    """The run form's boxes set (run_label= is #run-label)."""
    for name, value in values.items():
        box = driver.find_element("id", name.replace("_", "-"))
        box.clear()
        if value:
            box.send_keys(value)


def queue_rows(driver: Any) -> list[int]:
    """The entries the page shows waiting, in its order."""
    rows = driver.find_elements("css selector", "#queue tr.waiting")
    return [int(str(r.get_attribute("data-entry"))) for r in rows]


def queued_runs(c: Client, *entries: int) -> list[dict[str, Any]]:
    """The runs the queue started for `entries`, in the order they ran."""
    runs = [r for r in c.runs(100) if (r["settings"] or {}).get("queue_entry") in entries]
    return sorted(runs, key=lambda r: r["run_id"])


def test_runs_queued_from_the_page_wait_for_the_run_going(
    rig: dict[str, Any], browser: Any, shots: Path
) -> None:
    """Issue 38: the page submits to the queue (label, notes, priority); the run going is never
    ended for it; the page shows the queue as it changes, reorders an entry by its priority, asks
    before cancelling another's as an operator, pauses and resumes it; the queued runs then run
    after the run going, in the page's order."""
    browser.get(f"{rig['url']}?token={rig['token']}")
    wait_for("the control badge", lambda: body(browser, "control") == "yes")
    question = browser.find_element("id", "confirm")
    with Client(str(rig["sock"])) as c:
        theirs = c.start_cycling("15ms", 0, take_over=True, owner="lab script", label="overnight")["run_id"]
        wait_for("their run shown going", lambda: f"running: run {theirs}" in text(browser, "queue"))
        fill(browser, run_count="30", run_period="15", run_target="", run_priority="0")
        fill(browser, run_label="page-q", run_notes="queued from the page")
        browser.find_element("id", "submit").click()
        first = int(
            wait_for("the entry said", lambda: (m := text(browser, "notice")).startswith("queued") and m)
            .split()[3]
            .rstrip(",")
        )
        fill(browser, run_label="page-q2", run_notes="")
        browser.find_element("id", "submit").click()
        wait_for("two waiting", lambda: len(queue_rows(browser)) == 2)
        second = queue_rows(browser)[1]
        bobs = c.call("submit", 15_000_000, 3, None, False, "bobs", None, 0, False, BOB)["entry"]
        wait_for("bob's entry shown", lambda: queue_rows(browser) == [first, second, bobs])
        going = c.status()
        assert going["run"]["run_id"] == theirs and going["run"]["end_reason"] is None  # not ended
        row = browser.find_element("css selector", f'#queue tr[data-entry="{first}"]').text
        assert "page-q" in row and "panel" in row and "15.000 ms" in row and "30" in row, row
        assert "lab script" in text(browser, "queue") and "overnight" in text(browser, "queue")

        box = browser.find_element("css selector", f'#queue input.prio[data-entry="{second}"]')
        box.clear()
        box.send_keys("5")
        browser.find_element("css selector", f'#queue button.prio-set[data-entry="{second}"]').click()
        wait_for("reordered", lambda: queue_rows(browser) == [second, first, bobs])
        assert [e["entry"] for e in c.status()["queue"]["queued"]] == [second, first, bobs]

        browser.find_element("css selector", f'#queue button.cancel-entry[data-entry="{bobs}"]').click()
        wait_for("the page asking", question.is_displayed)
        asked = text(browser, "confirm-text")
        assert f"entry {bobs} is bob@elsewhere's" in asked and "as an operator?" in asked, asked
        browser.find_element("id", "confirm-yes").click()
        wait_for("bob's entry gone", lambda: queue_rows(browser) == [second, first])
        assert [e["entry"] for e in c.status()["queue"]["queued"]] == [second, first]

        browser.find_element("id", "queue-pause").click()
        wait_for("paused shown", lambda: body(browser, "queue-paused") == "yes")
        assert c.status()["queue"]["paused"] is True and "paused" in text(browser, "queue-state")
        browser.find_element("id", "queue-resume").click()
        wait_for("going on shown", lambda: body(browser, "queue-paused") == "no")
        assert c.status()["queue"]["paused"] is False

        browser.execute_script("document.getElementById('notice').hidden = true; window.scrollTo(0, 0)")
        start = int(body(browser, "strokes"))
        wait_for("a screenful of strokes", lambda: int(body(browser, "strokes")) >= start + 250, 15)
        browser.save_screenshot(str(shots / "panel-live.png"))

        c.stop_cycling()  # their run ends by their hand: the queue goes on, in the page's order
        wait_for(
            "both ran", lambda: [r["end_reason"] for r in queued_runs(c, first, second)] == ["done"] * 2, 60
        )
        ran = queued_runs(c, first, second)
        (ended,) = [r for r in c.runs(10) if r["run_id"] == theirs]
    assert ended["end_reason"] == "stopped"
    assert [r["settings"]["queue_entry"] for r in ran] == [second, first]
    assert [r["label"] for r in ran] == ["page-q2", "page-q"] and ran[1]["notes"] == "queued from the page"
    assert all(r["settings"]["owner"] == "panel" for r in ran) and ran[0]["first_cycle"] > ended["last_cycle"]
    wait_for("the queue emptied", lambda: "nothing going, nothing queued" in text(browser, "queue"))
    notes = f'#runs tr[data-run="{ran[1]["run_id"]}"] td.notes span'
    wait_for(
        "the notes listed", lambda: browser.find_element("css selector", notes).text == "queued from the page"
    )


def test_notes_edited_on_the_page_show_in_usmswitchctl_runs(rig: dict[str, Any], browser: Any) -> None:
    """Issue 38: a run's notes edited on the page (the panel's own run at once; another's after the
    page asks to act as an operator) are the records', as `usmswitchctl runs` reads them."""
    browser.get(f"{rig['url']}?token={rig['token']}")
    wait_for("the control badge", lambda: body(browser, "control") == "yes")
    with Client(str(rig["sock"])) as c:
        runs = c.runs(10)
    mine = [r for r in runs if r["settings"].get("owner") == "panel"][-1]["run_id"]
    theirs = [r for r in runs if r["settings"].get("owner") == "lab script"][-1]["run_id"]
    question = browser.find_element("id", "confirm")

    def edit(run_id: int, notes: str) -> None:
        button = f'#runs tr[data-run="{run_id}"] button.edit-notes'
        wait_for(f"run {run_id} listed", lambda: browser.find_elements("css selector", button))
        browser.find_element("css selector", button).click()
        wait_for("the notes form", browser.find_element("id", "notes-form").is_displayed)
        assert text(browser, "notes-run") == f"run {run_id}"
        fill(browser, notes_text=notes)
        browser.find_element("id", "notes-save").click()

    edit(mine, "edited on the page")
    cell = f'#runs tr[data-run="{mine}"] td.notes span'
    wait_for(
        "the notes shown", lambda: browser.find_element("css selector", cell).text == "edited on the page"
    )
    assert not question.is_displayed()
    edit(theirs, "seen from the panel")
    wait_for("the page asking", question.is_displayed)
    assert f"run {theirs} is lab script's" in text(browser, "confirm-text")
    browser.find_element("id", "confirm-yes").click()
    cell = f'#runs tr[data-run="{theirs}"] td.notes span'
    wait_for(
        "their notes shown", lambda: browser.find_element("css selector", cell).text == "seen from the panel"
    )
    cmd = [sys.executable, "-m", "usmswitch.client.ctl", "--socket", str(rig["sock"]), "runs", "-n", "10"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=True).stdout
    assert (
        f"run {mine} notes: edited on the page" in out and f"run {theirs} notes: seen from the panel" in out
    ), out


def test_the_runs_dates_are_iso_as_the_cli_writes_them(rig: dict[str, Any], browser: Any) -> None:
    """Issue 37's bites: the panel wrote the browser locale's dates (11/26/2025, 2:27:03 PM) where
    usmswitchctl writes ISO (2025-11-26 14:27:03)."""
    browser.get(f"{rig['url']}?token={rig['token']}")
    with Client(str(rig["sock"])) as c:
        runs = c.runs(3)
    for r in runs:
        want = datetime.datetime.fromtimestamp(r["started_wall_ns"] / 1e9).strftime("%Y-%m-%d %H:%M:%S")
        row = f'#runs tr[data-run="{r["run_id"]}"] td:nth-child(4)'
        wait_for(f"run {r['run_id']} listed", lambda row=row: browser.find_elements("css selector", row))
        assert browser.find_element("css selector", row).text == want


def test_the_urls_token_becomes_an_httponly_cookie_and_leaves_every_url(
    rig: dict[str, Any], browser: Any
) -> None:
    """Issue 35, item 11: the token rode in the URL: in the Referer of 4 asset requests, in
    Chromium's history and cache, and in a proxy's log. The server now trades it for a cookie the
    page's script cannot read and redirects to the clean URL before the page loads."""
    browser.delete_all_cookies()
    browser.get(f"{rig['url']}?token={rig['token']}")
    wait_for("the control badge", lambda: body(browser, "control") == "yes")
    assert browser.current_url == rig["url"]
    cookie = browser.get_cookie("usmswitch_token")
    assert cookie is not None and cookie["value"] == rig["token"]
    assert cookie["httpOnly"] is True and cookie["sameSite"] == "Strict"
    assert rig["token"] not in browser.execute_script("return document.cookie")
    history = browser.execute_cdp_cmd("Page.getNavigationHistory", {})["entries"]
    assert history and not any(rig["token"] in e["url"] for e in history), history
    # Every resource the page fetched was asked for under a URL without the token.
    names = browser.execute_script("return performance.getEntries().map(e => e.name)")
    assert names and not any(rig["token"] in n for n in names), names


def test_without_the_token_the_page_is_refused(rig: dict[str, Any], browser: Any, shots: Path) -> None:
    with Client(str(rig["sock"])) as c:  # a run going and two waiting: the queue shown, read-only
        c.start_cycling("15ms", 0, take_over=True, owner="lab script", label="overnight")
        waiting = [c.submit_entry("15ms", 200, label=name)["entry"] for name in ("sweep-12ms", "sweep-13ms")]
    browser.delete_all_cookies()  # the token's cookie from the tests before
    browser.get(rig["url"])
    wait_for("the read-only badge", lambda: body(browser, "control") == "no")
    assert text(browser, "access") == "read-only"
    wait_for("strokes", lambda: int(body(browser, "strokes")) > 10)
    wait_for("the queue shown", lambda: queue_rows(browser) == waiting)
    # The queue's and the notes' controls are absent; its forms' buttons are refused as the others.
    for css in ("#queue input.prio", "#queue button", "#runs button.edit-notes"):
        shown = [e for e in browser.find_elements("css selector", css) if e.is_displayed()]
        assert not shown, css
    assert not browser.find_element("id", "queue-pause").is_displayed()
    for button in ("stop", "submit", "estop"):
        browser.find_element("id", button).click()
        wait_for("the refusal shown", lambda: "read-only" in text(browser, "notice"))
        assert "usmswitchctl web-url" in text(browser, "notice")
        browser.execute_script("document.getElementById('notice').hidden = true")
    browser.find_element("id", "estop").click()
    wait_for("the refusal shown", lambda: "read-only" in text(browser, "notice"))
    with Client(str(rig["sock"])) as c:
        assert c.status()["state"] == "cycling"
        assert [e["entry"] for e in c.status()["queue"]["queued"]] == waiting  # nothing queued from here
        browser.save_screenshot(str(shots / "panel-readonly.png"))
        for entry in waiting:  # the estop's test after this one resets a fault: nothing to start then
            c.queue_cancel(entry, operator=True)


def test_the_estop_with_the_token_latches_fault(rig: dict[str, Any], browser: Any) -> None:
    """The page's estop latches FAULT. How fast is the bench's to say (make bench BENCH=abuse, the
    panel path): a test asserting 100 ms failed on a loaded machine (145-358 ms, 7f3fa01 too), a
    wall-clock claim a test cannot judge there; here, within a second, and the time is printed."""
    browser.get(f"{rig['url']}?token={rig['token']}")
    wait_for("the control badge", lambda: body(browser, "control") == "yes")
    estop = browser.find_element("id", "estop")
    with Client(str(rig["sock"])) as c:
        assert c.status()["state"] == "cycling"
        t0 = time.monotonic()
        estop.click()
        while (state := c.status()) and state["state"] != "fault":
            assert time.monotonic() - t0 < 1.0, "no FAULT 1 s after the estop"
        took = time.monotonic() - t0
        print(f"\npanel estop: FAULT latched {took * 1e3:.1f} ms after the click (Selenium's click included)")
        # On the feed the page holds open (issue 35); "estop (panel, estop socket)" is the POST's.
        # was "estop (socket)" (issue 37's bites); by the estop socket from the HTTP doors' thread
        assert state["fault"] == "estop (panel, live feed, estop socket)"
        shown = "FAULT latched: estop (panel, live feed, estop socket)"
        wait_for("the fault shown", lambda: shown in text(browser, "fault"))
        browser.find_element("id", "reset").click()
        wait_for("the fault reset", lambda: c.status()["state"] != "fault")
        # With the feed down (closing; it reconnects within a second), the estop goes by POST.
        browser.execute_script("feed.close();")
        estop.click()
        wait_for("the POST's estop", lambda: c.status()["fault"] == "estop (panel, estop socket)")
        browser.find_element("id", "reset").click()
        wait_for("the fault reset", lambda: c.status()["state"] != "fault")
