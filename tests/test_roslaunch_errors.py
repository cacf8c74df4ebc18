"""A node type roslaunch cannot find is said as roslaunch says it, with the Debian package
that is missing where the file layout tells (issue 33, item 12): it never ran, so it is not
a node that "exited"."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from perfros_bag.errors import PerfrosError
from perfros_bag.sweep import runner
from perfros_bag.sweep.runner import _died_line, debian_package_known, missing_package

# what Debian's roslaunch writes when rospack cannot find a node's package
LOG = ("... logging to /tmp/x/roslaunch-host-1.log\n"
       "\x1b[1mstarted roslaunch server http://127.0.0.1:40001/\x1b[0m\n"
       "ERROR: cannot launch node of type [topic_tools/throttle]: topic_tools\n"
       "ROS path [0]=/usr/share/ros\nROS path [1]=/usr/share\n")


def _layout(tmp_path: Path, *, exe: bool, xml: bool) -> tuple[Path, Path]:
    share, lib = tmp_path / "share", tmp_path / "lib"
    if exe:
        (lib / "topic_tools").mkdir(parents=True)
        (lib / "topic_tools" / "throttle").write_text("#!/bin/sh\n")
    if xml:
        (share / "topic_tools").mkdir(parents=True)
        (share / "topic_tools" / "package.xml").write_text("<package/>")
    return share, lib


def test_debian_package_known_asks_apt() -> None:
    import shutil
    import subprocess

    apt = shutil.which("apt-cache")
    assert apt is not None, "this test machine has Debian's apt"
    listed = subprocess.run([apt, "pkgnames", "libtopic-tools"], capture_output=True, text=True).stdout.split()
    assert debian_package_known("libtopic-tools-dev") == ("libtopic-tools-dev" in listed)
    assert not debian_package_known("libperfros-no-such-package-dev")


def test_an_executable_without_its_package_xml_names_the_dev_package(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """topic-tools installed, libtopic-tools-dev (its package.xml) not: the case the issue met."""
    share, lib = _layout(tmp_path, exe=True, xml=False)
    monkeypatch.setattr(runner, "DEBIAN_SHARE", share)
    monkeypatch.setattr(runner, "DEBIAN_LIB", lib)
    log = tmp_path / "roslaunch.log"
    log.write_text(LOG)
    with pytest.raises(PerfrosError) as caught:
        _died_line(log)
    text = str(caught.value)
    assert text.startswith("roslaunch cannot launch node of type [topic_tools/throttle]: topic_tools; ")
    assert f"{lib}/topic_tools/throttle is installed but not {share}/topic_tools/package.xml" in text
    assert "exited" not in text and str(log) in text
    if debian_package_known("libtopic-tools-dev"):
        assert "Debian ships it in libtopic-tools-dev (apt-get install libtopic-tools-dev)" in text


def test_what_the_layout_tells_in_each_case(tmp_path: Path) -> None:
    share, lib = _layout(tmp_path, exe=False, xml=False)
    assert missing_package("topic_tools/throttle", share, lib).startswith(  # type: ignore[union-attr]
        "the ROS package topic_tools is not installed")
    share, lib = _layout(tmp_path / "b", exe=False, xml=True)
    assert missing_package("topic_tools/throttle", share, lib) \
        == f"the package topic_tools has no executable throttle in {lib}/topic_tools"
    share, lib = _layout(tmp_path / "c", exe=True, xml=True)
    assert missing_package("topic_tools/throttle", share, lib) is None  # both there: another cause
    assert missing_package("../etc/passwd", share, lib) is None  # no path games with the log's text


@pytest.mark.ros
def test_sweep_says_roslaunch_cannot_launch_a_node_of_a_package_not_installed(tmp_path: Path) -> None:
    from tests.test_sweep_e2e import APP, _cli, _require_ros

    _require_ros()
    launch = tmp_path / "app.launch"
    launch.write_text(APP.read_text().replace(
        "</launch>", '<node name="ghost" pkg="perfros_no_such_pkg" type="ghost_node" /></launch>').replace(
        "$(dirname)/circles.png", str(APP.with_name("circles.png"))))
    space = tmp_path / "space.yaml"
    space.write_text(yaml.safe_dump({"duration_s": 2, "settle_s": 1, "startup_timeout_s": 30, "vary": [
        {"node": "camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate", "values": [5]}]}))
    done = _cli("sweep", str(launch), "--space", str(space), "--out", str(tmp_path / "out"))
    assert done.returncode == 2, done.stderr
    lines = [ln for ln in done.stderr.splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert len(lines) == 1, done.stderr
    assert "roslaunch cannot launch node of type [perfros_no_such_pkg/ghost_node]" in lines[0]
    assert "the ROS package perfros_no_such_pkg is not installed" in lines[0] and "exited" not in lines[0]
