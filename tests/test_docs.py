"""The documentation site builds in strict mode (a broken link or reference, or a tutorial whose
stored outputs were made by other code, fails it): the API reference from the docstrings, the
notebooks as tutorials with their outputs, the Drake name map. It asks for nothing on the
network: in a headless Chromium kept offline, a tutorial shows its plots and its math typeset by
the KaTeX shipped with the site.

Chromium is Debian's (`apt-get install chromium`; `.ci/run` installs it): the browser tests skip
where it is missing, and fail under CI."""

import copy
import fcntl
import html
import html.parser
import importlib
import importlib.util
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
TUTORIALS = sorted((ROOT / "docs" / "tutorials").glob("*.ipynb"))
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _tutorial_outputs():
    pytest.importorskip("mkdocs")  # the script is also the site's mkdocs hook
    spec = importlib.util.spec_from_file_location("tutorial_outputs", ROOT / "scripts" / "tutorial_outputs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    path = tmp_path_factory.mktemp("site")
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, env=dict(os.environ, NO_MKDOCS_2_WARNING="1"))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "WARNING" not in done.stderr, done.stderr[-3000:]
    return path


def test_the_docs_build_in_strict_mode(site):
    reference = (site / "api/simulation/index.html").read_text()
    assert 'id="jaxdrake.simulation.simulate"' in reference  # rendered from the docstring
    assert (site / "tutorials/limit_cycles/index.html").exists()
    drake = (site / "from_drake/index.html").read_text()
    for name in ("DrakeSystem", "HybridDrakeSystem", "LinearQuadraticRegulator", "runLCM"):
        assert name in drake, name


class _Resources(html.parser.HTMLParser):
    """The URLs a page loads by itself (scripts, stylesheets, images, frames), not the links."""

    def __init__(self):
        super().__init__()
        self.urls = []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag in ("script", "img", "iframe", "source", "video", "audio") and attrs.get("src"):
            self.urls.append(attrs["src"])
        if tag == "link" and {"stylesheet", "preload", "icon", "modulepreload"} & set((attrs.get("rel") or "").split()):
            self.urls.append(attrs.get("href") or "")


def test_every_page_loads_only_files_of_the_site(site):
    """No CDN: every script, stylesheet and image is a file of the site (or inline data)."""
    remote = re.compile(r"^(https?:)?//", re.IGNORECASE)
    for page in site.rglob("*.html"):
        parser = _Resources()
        parser.feed(page.read_text())
        assert parser.urls, page
        assert not [url for url in parser.urls if remote.match(url)], page
    for sheet in site.rglob("*.css"):
        assert not re.search(r"url\(\s*['\"]?(https?:)?//", sheet.read_text()), sheet


def test_the_api_pages_put_the_entry_points_first_with_their_types(site):
    simulation = (site / "api/simulation/index.html").read_text()
    order = [simulation.index(f'id="jaxdrake.simulation.{name}"')
             for name in ("simulate", "SimulatedTrajectory", "Dopri5", "IController")]
    assert order == sorted(order)
    start = simulation.index("doc-signature", order[0])
    signature = html.unescape(re.sub(r"<[^>]+>", "", simulation[start:simulation.index("</code>", start)]))
    assert "simulate(system: System," in signature and signature.rstrip().endswith("-> SimulatedTrajectory")
    # the split into entry points and the rest loses no public class or function with a docstring
    for package in ("simulation", "systems", "trajectories", "control", "trajopt", "viz", "multibody", "polynomials",
                    "mujoco"):
        page = (site / f"api/{package}/index.html").read_text()
        module = importlib.import_module(f"jaxdrake.{package}")
        documented = [name for name in module.__all__ if _has_docstring(getattr(module, name))]
        missing = [name for name in documented if f'id="jaxdrake.{package}.{name}"' not in page]
        assert not missing, (package, missing)


def _has_docstring(obj):
    """A function's or class's own docstring (not one that dataclasses write for a class)."""
    if isinstance(obj, type):
        doc = vars(obj).get("__doc__")
        return bool(doc) and not doc.startswith(f"{obj.__name__}(")
    return callable(obj) and bool(obj.__doc__)


def test_the_tutorials_outputs_are_stored_and_made_by_their_code():
    """Each tutorial's stored outputs come from one run, top to bottom, of its current code,
    with no error and at least one plot."""
    outputs = _tutorial_outputs()
    for path in TUTORIALS:
        notebook = json.loads(path.read_text())
        stored_path = outputs.OUTPUTS / f"{path.stem}.json"
        assert stored_path.exists(), f"run `{outputs.RENDER} {path.stem}`"
        stored = json.loads(stored_path.read_text())
        assert outputs.stale_cells(notebook, stored) == [], f"run `{outputs.RENDER} {path.stem}`"
        cells = stored["cells"]
        assert [cell["execution_count"] for cell in cells] == list(range(1, len(cells) + 1)), path.stem
        kinds = [output["output_type"] for cell in cells for output in cell["outputs"]]
        assert "error" not in kinds, path.stem
        assert any("image/png" in output.get("data", {}) for cell in cells for output in cell["outputs"]), path.stem


def test_a_change_to_code_marks_its_outputs_and_those_below_stale():
    outputs = _tutorial_outputs()
    notebook = json.loads((ROOT / "notebooks" / "simple_systems.ipynb").read_text())
    stored = {"cells": [{"code_sha256": h} for h in outputs.code_hashes(notebook)]}
    code = [i for i, cell in enumerate(notebook["cells"]) if cell["cell_type"] == "code"]
    prose = next(i for i, cell in enumerate(notebook["cells"]) if cell["cell_type"] == "markdown")
    for edited, stale in ((code[1], list(range(1, len(code)))), (code[-1], [len(code) - 1]), (prose, [])):
        changed = copy.deepcopy(notebook)
        changed["cells"][edited]["source"] = ["# edited\n"] + list(changed["cells"][edited]["source"])
        assert outputs.stale_cells(changed, stored) == stale
    longer = copy.deepcopy(notebook)
    longer["cells"].append({"cell_type": "code", "source": ["1"], "metadata": {}, "outputs": []})
    assert outputs.stale_cells(longer, stored) == [len(code)]


class Chromium:
    """Debian's Chromium, headless, driven through its DevTools protocol over the debugging
    pipe (JSON messages ended by NUL; Chromium reads fd 3 and writes fd 4): no socket at all.
    Its host resolver answers no name but 127.0.0.1, and each page runs with the network off."""

    def __init__(self, profile):
        ours_read, theirs_write = os.pipe()
        theirs_read, ours_write = os.pipe()
        # Chromium's ends on descriptors above 3 and 4 before bash moves them there
        theirs = [fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (theirs_read, theirs_write)]
        for fd in (theirs_read, theirs_write):
            os.close(fd)
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe", f"--user-data-dir={profile}",
                 "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--disable-extensions", "about:blank"]
        self.process = subprocess.Popen(
            ["bash", "-c", f'exec "$0" "$@" 3<&{theirs[0]} 4>&{theirs[1]} {theirs[0]}<&- {theirs[1]}>&-', CHROMIUM,
             *flags], pass_fds=theirs, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for fd in theirs:
            os.close(fd)
        self.reader, self.writer = ours_read, os.fdopen(ours_write, "wb")
        self.received, self.events, self.last_id = b"", [], 0
        target = self.send("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.send("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Network"):
            self.send(f"{domain}.enable", self.session)
        self.send("Network.emulateNetworkConditions", self.session, offline=True, latency=0, downloadThroughput=-1,
                  uploadThroughput=-1)

    def send(self, method, session=None, **params):
        """Send a command; its result (events read meanwhile are kept in `events`)."""
        self.last_id += 1
        message = {"id": self.last_id, "method": method, "params": params} | ({"sessionId": session} if session else {})
        self.writer.write(json.dumps(message).encode() + b"\0")
        self.writer.flush()
        while True:
            reply = self._next()
            if reply.get("id") == self.last_id:
                assert "error" not in reply, (method, reply["error"])
                return reply["result"]
            self.events.append(reply)

    def _next(self):
        while b"\0" not in self.received:
            chunk = os.read(self.reader, 1 << 16)
            assert chunk, "Chromium closed its pipe"
            self.received += chunk
        message, self.received = self.received.split(b"\0", 1)
        return json.loads(message)

    def open(self, url):
        """Load url and wait for its load event (its scripts have run, its images loaded);
        the URLs it requested."""
        self.events.clear()
        self.send("Page.navigate", self.session, url=url)
        while not any(event.get("method") == "Page.loadEventFired" for event in self.events):
            self.events.append(self._next())
        return [event["params"]["request"]["url"] for event in self.events
                if event.get("method") == "Network.requestWillBeSent"]

    def evaluate(self, expression):
        return self.send("Runtime.evaluate", self.session, expression=expression, returnByValue=True)["result"]["value"]

    def close(self):
        self.send("Browser.close")
        self.process.wait(timeout=30)
        os.close(self.reader)
        self.writer.close()


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    if not CHROMIUM:
        reason = "Chromium is not installed (apt-get install chromium; .ci/run does)"
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)
    chromium = Chromium(tmp_path_factory.mktemp("chromium-profile"))
    yield chromium
    chromium.close()


# what a page shows: its plots' sizes, KaTeX's output, its failures, and math left as TeX source
# outside code (an arithmatex element with no KaTeX in it, or $...$ in a notebook's Markdown)
PAGE = """(() => {
  const untypeset = [...document.querySelectorAll('.arithmatex')].filter(e => !e.querySelector('.katex'));
  const prose = [...document.querySelectorAll('.jp-RenderedMarkdown')].map(cell => {
    const copy = cell.cloneNode(true);
    copy.querySelectorAll('.katex, code, pre').forEach(e => e.remove());
    return copy.textContent;
  }).join(' ');
  return {plots: [...document.querySelectorAll('.jp-OutputArea-output img')].map(img => img.naturalWidth),
          images: [...document.querySelectorAll('article img')].map(img => img.naturalWidth),
          katex: document.querySelectorAll('.katex').length,
          errors: [...document.querySelectorAll('.katex-error')].map(e => e.title),
          raw: untypeset.map(e => e.textContent).concat(prose.match(/\\$[^$]+\\$/g) || [])};
})()"""


def _local(urls):
    return [url for url in urls if not url.startswith(("file:", "data:", "about:"))]


def test_a_tutorial_shows_its_plots_and_typeset_math_offline(site, browser):
    outputs = _tutorial_outputs()
    stored = json.loads((outputs.OUTPUTS / "simple_systems.json").read_text())
    plots = [output for cell in stored["cells"] for output in cell["outputs"] if "image/png" in output.get("data", {})]
    requested = browser.open((site / "tutorials/simple_systems/index.html").as_uri())
    assert not _local(requested), requested
    page = browser.evaluate(PAGE)
    assert len(page["plots"]) == len(plots) > 0 and all(width > 0 for width in page["plots"]), page["plots"]
    assert page["katex"] > 0 and not page["errors"] and not page["raw"], page
    typeset = browser.evaluate("[...document.querySelectorAll('.katex annotation')].map(a => a.textContent)")
    assert "\\dot x = -x + x^3" in typeset  # the notebook's $\dot x = -x + x^3$, now KaTeX's


def test_the_home_page_shows_its_picture_offline(site, browser):
    requested = browser.open((site / "index.html").as_uri())
    assert not _local(requested), requested
    page = browser.evaluate(PAGE)
    assert page["images"] == [1300]  # examples/demo.py's figure, 1300 x 900


# pages whose math KaTeX refuses, with the reason; a fixed one must leave this list
KNOWN_MATH_ERRORS: dict[str, str] = {}


@pytest.mark.slow  # ~25 s for the ~40 pages on 2 cores; by default the tutorial and home page tests above
def test_every_page_shows_its_pictures_and_typesets_its_math_offline(site, browser):
    failures = {}
    for page in sorted(site.rglob("index.html")):
        name = str(page.relative_to(site))
        requested = _local(browser.open(page.as_uri()))
        shown = browser.evaluate(PAGE)
        unloaded = [width for width in shown["images"] if width == 0]
        no_plot = name.startswith("tutorials/") and not shown["plots"]
        if requested or unloaded or no_plot or shown["errors"] or shown["raw"]:
            failures[name] = {"requested": requested, "unloaded": unloaded, "no plot": no_plot,
                              "errors": shown["errors"], "raw": shown["raw"]}
    assert failures.keys() == KNOWN_MATH_ERRORS.keys(), failures
