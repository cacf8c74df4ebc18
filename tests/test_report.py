"""report: the HTML page, its plots, escaping, and rendering in headless Chromium."""

from __future__ import annotations

import base64
import html.parser
import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from test_validate import PLAN, stats_at  # tests/ is on sys.path (no package)
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import InputError
from perfros_bag.fitting.modelfile import MODEL_FORMAT
from perfros_bag.report.html import build_report
from perfros_bag.system.planfile import parse_plan
from perfros_bag.validation.eq10 import check_run

EVIL = '<script>alert("x")</script>&$\\frac{a$'  # HTML specials; $ would be mathtext
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class Collector(html.parser.HTMLParser):
    """Tables (by id) as lists of rows of cell text; <script> tags; image sources."""

    def __init__(self) -> None:
        super().__init__()
        self.tables: dict[str, list[list[str]]] = {}
        self.scripts = 0
        self.images: list[str] = []
        self._table: str | None = None
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "script":
            self.scripts += 1
        elif tag == "img":
            self.images.append(a.get("src") or "")
        elif tag == "table":
            self._table = a.get("id") or f"table{len(self.tables)}"
            self.tables[self._table] = []
        elif tag == "tr" and self._table:
            self.tables[self._table].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "th") and self._cell is not None and self._table:
            self.tables[self._table][-1].append("".join(self._cell))
            self._cell = None
        elif tag == "table":
            self._table = None

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def inputs(tmp: Path) -> dict[str, Path]:
    plan_data = json.loads(json.dumps(PLAN))
    plan_data["nodes"][EVIL] = plan_data["nodes"].pop("b")
    (tmp / "plan.json").write_text(json.dumps(plan_data))
    v = check_run(stats_at(0.8, drop=("/b/y",)), parse_plan(plan_data, "plan.json"))
    (tmp / "validation.json").write_text(json.dumps(v.to_dict()))
    model = {"format": MODEL_FORMAT, "system_file": "s.yaml", "characterisation": "char.csv", "system": {}, "fits": {
        "tracker": {"parameter->cpu": {"form": "linear", "coef": [8.0, 0.0], "domain": [10, 25], "scale": 1,
                                        "r2": 1.0, "points": [[10, 80], [15, 120], [20, 160], [25, 200]]},
                    "cpu->performance": {"form": "log", "coef": [66.62, 56.308], "domain": [80, 200],
                                         "scale": 100, "r2": 0.99, "points": [[80, 40], [120, 70], [200, 100]]}},
        EVIL: {"parameter->cpu": {"form": "linear", "coef": [1, 2], "domain": [1, 2], "r2": 1.0,
                                  "points": [[1, 3], [2, 4]]}},
        "not_fitted": {},
    }}
    (tmp / "model.json").write_text(json.dumps(model))
    (tmp / "char.csv").write_text(
        "recording,node,parameter,value,topic,msgtype,messages,duration_s,frequency_hz,bandwidth_kBps,"
        "cpu_units_mean,cpu_units_p95,cpu_samples\n"
        f'r1.bag,tracker,output_freq,10,/tracker/tracks,std_msgs/String,101,10.0,10.0,1.0,80.5,82.1,10\n'
        f'"{EVIL.replace(chr(34), chr(34) * 2)}",amcl,particles,200,/amcl_pose,x,26,10.0,2.5,0.1,19.2,20.0,10\n')
    return {"plan": tmp / "plan.json", "validation": tmp / "validation.json", "model": tmp / "model.json",
            "characterisation": tmp / "char.csv"}


@pytest.fixture(scope="module")
def full_report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The report of every input, built once for the module."""
    tmp = tmp_path_factory.mktemp("report")
    return build_report(tmp / "report", **inputs(tmp))  # type: ignore[arg-type]


def test_report_sections_tables_and_images(full_report: Path) -> None:
    text = full_report.read_text()
    assert "<script>" not in text and "&lt;script&gt;" in text  # escaped everywhere
    c = Collector()
    c.feed(text)
    assert c.scripts == 0
    plan_rows = c.tables["plan-table"]
    assert plan_rows[0][:4] == ["computer", "kind", "capacity", "planned CPU"]
    assert {r[0]: r[4] for r in plan_rows[1:]} == {"robot1": "a (rate=10)", "server": EVIL}
    val = {r[0]: r for r in c.tables["validation-table"][1:]}
    assert set(val) == {"a", EVIL}
    assert val["a"][3:6] == ["80", "64", "20"]  # P expected, P measured (0.8), deviation %
    assert "(missing)" in val[EVIL][2] and "/b/x: 16 / 20 Hz" in val[EVIL][2]
    fits = c.tables["fits-table"]
    assert {(r[0], r[1]) for r in fits[1:]} == {("tracker", "parameter->cpu"), ("tracker", "cpu->performance"),
                                                 (EVIL, "parameter->cpu")}
    chars = c.tables["characterisation-table"]
    assert chars[0][0] == "recording" and chars[2][0] == EVIL and len(chars) == 3
    # every image is an inlined PNG, also written beside the page
    assert len(c.images) == 4  # plan, validation, two fit figures (none for the node without fits)
    for src in c.images:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1]).startswith(PNG_MAGIC)
    pngs = sorted(p.name for p in full_report.parent.glob("*.png"))
    assert pngs == ["fit_00.png", "fit_01.png", "plan_cpu.png", "validation.png"]


def test_missing_parts_are_left_out(tmp_path: Path) -> None:
    files = inputs(tmp_path)
    text = build_report(tmp_path / "r", plan=files["plan"]).read_text()
    assert 'id="plan-table"' in text and "validation-table" not in text and "fits-table" not in text
    text = build_report(tmp_path / "r2").read_text()
    assert "Nothing to report" in text


def test_cli_report_and_bad_input(tmp_path: Path) -> None:
    files = inputs(tmp_path)
    runner = CliRunner()
    r = runner.invoke(app, ["report", "--plan", str(files["plan"]), "--validation", str(files["validation"]),
                            "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "rep" / "index.html").is_file()
    (tmp_path / "bad.json").write_text("[1, 2]")
    for opt, path in (("--validation", tmp_path / "bad.json"), ("--plan", tmp_path / "nope.json"),
                      ("--model", tmp_path / "bad.json")):
        r = runner.invoke(app, ["report", opt, str(path), "--out", str(tmp_path / "bad")])
        assert r.exit_code == 2, r.output
        assert path.name in r.output and "Traceback" not in r.output
    assert not (tmp_path / "bad").exists()


def test_report_reads_model_and_csv_with_their_checks(tmp_path: Path) -> None:
    """The report reads model.json and characterisation.csv with the readers fit uses: a
    broken fit or a CSV without the required columns is one error line naming the place."""
    files = inputs(tmp_path)
    model = json.loads(files["model"].read_text())
    model["fits"]["tracker"]["cpu->performance"]["coef"][1] = "x"
    (tmp_path / "badfit.json").write_text(json.dumps(model))
    (tmp_path / "badchar.csv").write_text("recording,node\nr.bag,a\n")
    runner = CliRunner()
    for opt, path, problem in (
            ("--model", tmp_path / "badfit.json", "fits.tracker.cpu->performance.coef[1]: expected a number, got 'x'"),
            ("--characterisation", tmp_path / "badchar.csv", "not a characterisation.csv: missing column(s) value")):
        r = runner.invoke(app, ["report", opt, str(path), "--out", str(tmp_path / "bad")])
        assert r.exit_code == 2, r.output
        errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
        assert len(errors) == 1 and f"{path}: {problem}" in errors[0], r.stderr
        assert "Traceback" not in r.output
    assert not (tmp_path / "bad").exists()


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("chromium is not installed: run make setup-debs (apt-get install chromium)")
    return exe


def run_chromium(tmp: Path, *args: str) -> subprocess.CompletedProcess[str]:
    cmd = [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
           f"--user-data-dir={tmp / 'chromium-profile'}", "--enable-logging=stderr", "--v=0", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def test_report_renders_in_headless_chromium(full_report: Path, tmp_path: Path) -> None:
    url = full_report.resolve().as_uri()
    dom = run_chromium(tmp_path, "--dump-dom", url)
    assert dom.returncode == 0, dom.stderr[-2000:]
    c = Collector()
    c.feed(dom.stdout)
    assert "plan-table" in c.tables and len(c.tables["plan-table"]) == 3
    assert c.scripts == 0  # the evil node name stayed text
    for log in (dom.stderr,):
        assert "Uncaught" not in log and "ERROR:CONSOLE" not in log
    shot = tmp_path / "shot.png"
    r = run_chromium(tmp_path, f"--screenshot={shot}", "--window-size=1200,2400", "--hide-scrollbars", url)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Uncaught" not in r.stderr and "ERROR:CONSOLE" not in r.stderr
    assert shot.read_bytes().startswith(PNG_MAGIC) and shot.stat().st_size > 20_000
    keep: Any = __import__("os").environ.get("PERFROS_KEEP_SCREENSHOT")
    if keep:
        shutil.copy(shot, keep)


def test_validation_plot_of_many_nodes_keeps_the_largest_deviations(tmp_path: Path) -> None:
    from perfros_bag.report import validation_plots as report

    nodes = [{"node": f"n{i}", "p_expected": 10.0, "p_measured": 10.0 - i % 7, "deviation_pct": 10.0 * (i % 7)}
             for i in range(300)]
    v = {"nodes": nodes, "overall": {"expected": 1.0, "measured": 0.9, "deviation_pct": 10.0}}
    png = report.plot_validation(v)
    assert png.startswith(PNG_MAGIC)
    import struct

    width = struct.unpack(">I", png[16:20])[0]
    assert width < 100 * (0.8 * report.MAX_PLOT_NODES + 4) * 1.1  # capped, not 300 bars wide


@pytest.mark.parametrize(("number", "needle"), [
    ("NaN", "must be a finite number"), ("Infinity", "must be a finite number"),
    ("1e308", "must be at most 1e+12 in magnitude"),
])
def test_a_validation_with_unprintable_numbers_is_refused_with_the_place(
        tmp_path: Path, number: str, needle: str) -> None:
    files = inputs(tmp_path)
    doc = json.loads(files["validation"].read_text())
    doc["nodes"][0]["p_measured"] = "__N__"
    bad = tmp_path / "bad-validation.json"
    bad.write_text(json.dumps(doc).replace('"__N__"', number))
    with pytest.raises(InputError) as info:
        build_report(tmp_path / "out", validation=bad)
    assert str(info.value).startswith(f"{bad}: nodes[0].p_measured: {needle}")
    assert not (tmp_path / "out" / "index.html").exists()
