"""The top-level command group: each verb's module is imported only when that verb runs.

``perfros-bag --help`` lists the verbs from :data:`VERBS` (name -> module, one-line help)
without importing any verb module; ``perfros-bag VERB ...`` imports ``VERB``'s module alone,
which registers its command on :data:`perfros_bag.cli._app.app` (tests check that the table
matches the modules' real commands).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, NamedTuple

import typer
from typer.core import TyperCommand, TyperGroup, TyperOption

if TYPE_CHECKING:
    # the Context class typer's groups are declared with (typer's bundled click)
    from typer import _click as click


class Verb(NamedTuple):
    """Where a verb is defined and what ``--help`` says about it."""

    module: str
    help: str  # the first paragraph of the command's docstring, as the real command shows it


#: Every verb, in the order ``--help`` lists them.
VERBS: Mapping[str, Verb] = {
    "characterise": Verb("perfros_bag.cli.characterise", "Characterise every recording in DIR: per node and "
                         "topic, frequency, bandwidth and CPU."),
    "export": Verb("perfros_bag.cli.export",
                   "Write a plan as a ROS 1 launch file (yours, with --launch) or ROS 2 files."),
    "fit": Verb("perfros_bag.cli.fit", "Fit parameter -> CPU/performance/frequency/bandwidth and CPU -> "
                "performance per configurable node."),
    "info": Verb("perfros_bag.cli.info", "Per-topic table like `rosbag info` / `ros2 bag info`, with rates and "
                 "bandwidth."),
    "record-cpu": Verb("perfros_bag.cli.record_cpu", "Sample CPU % and RSS of matching processes until the "
                       "duration ends, Ctrl-C, or COMMAND exits."),
    "report": Verb("perfros_bag.cli.report", "Write an HTML report; anything not given is left out."),
    "solve": Verb("perfros_bag.cli.solve", "Choose a setting and a computer for every node (the paper's "
                  "Problems 1 and 2)."),
    "validate": Verb("perfros_bag.cli.validate", "Compare a run with its plan (the paper's eq 10); exit 1 when "
                     "the overall deviation\nexceeds --tolerance."),
    "version": Verb("perfros_bag.cli.version", "Print perfros-bag's version."),
    "sweep": Verb("perfros_bag.cli.sweep", "Run APP.launch once per setting of space.yaml; record every topic "
                  "and the nodes' CPU."),
    "init": Verb("perfros_bag.cli.init", "Draft system.yaml from DIR's graph.yaml, manifest and recordings "
                 "(loads, fits and solves as it is)."),
    "deploy": Verb("perfros_bag.cli.deploy", "Run PLAN on this machine (capped cgroups, shaped links), "
                   "record it and validate it (eq 10)."),
    "tune": Verb("perfros_bag.cli.tune", "Sweep, fit, solve and deploy APP.launch, then refit on each deployment "
                 "until its plan holds."),
    "watch": Verb("perfros_bag.cli.watch", "Watch a running plan live: rates, CPU, links and eq 10 per window; "
                  "alarms on persisting drift."),
    "casestudy": Verb("perfros_bag.cli.casestudy", "The paper's case study on real ROS 1 nodes (roscore, rospy, "
                      "rosbag)."),
}


class _Unloaded(TyperCommand):
    """A verb whose module is not imported yet: its name and one-line help only."""


def load_verb(name: str) -> TyperCommand | TyperGroup:
    """Import ``name``'s module and return the click command it registered."""
    from perfros_bag.cli._app import app, err

    try:
        importlib.import_module(VERBS[name].module)
    except KeyboardInterrupt:  # Ctrl-C while still importing: as inside a verb
        err.print("[red]interrupted[/]")
        raise typer.Exit(130) from None
    command = typer.main.get_group(app).commands.get(name)
    if not isinstance(command, TyperCommand | TyperGroup):
        raise LookupError(f"{VERBS[name].module} does not define the command {name!r}")
    return command


class QuickHelpGroup(TyperGroup):
    """A TyperGroup whose ``--help`` flag, when not given, is False rather than None.

    For None typer builds a pydantic validator, and importing pydantic costs ~50 ms of every
    ``perfros-bag VERB --help`` (typer 0.29); for a bool it has nothing to check.
    """

    def get_help_option(self, ctx: click.Context) -> TyperOption | None:
        option = super().get_help_option(ctx)
        if option is not None and option.default is None:
            option.default = False
        return option


class LazyVerbGroup(QuickHelpGroup):
    """A TyperGroup that lists :data:`VERBS` as they are and imports a verb on first use."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        loaded = self.commands  # the verbs whose modules are imported already
        ordered: dict[str, click.Command] = {
            name: loaded.get(name) or _Unloaded(name, help=verb.help) for name, verb in VERBS.items()}
        # a command registered outside the table stays reachable (a test keeps the table whole)
        ordered.update((name, cmd) for name, cmd in loaded.items() if name not in VERBS)
        self.commands = ordered
        self._listing = False

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        command = self.commands.get(cmd_name)
        if isinstance(command, _Unloaded) and not self._listing:
            command = self.commands[cmd_name] = load_verb(cmd_name)
        return command

    def format_help(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        self._listing = True  # the verb list needs names and one-line helps only
        try:
            super().format_help(ctx, formatter)
        finally:
            self._listing = False
