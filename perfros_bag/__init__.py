"""perfros-bag: performance-driven configuration of distributed ROS applications.

The library is importable on its own; ``perfros_bag.cli`` is a thin typer layer over it.
The names below are the public API, one per stage of the pipeline. They are imported on
first use (PEP 562), so ``import perfros_bag`` stays light::

    import perfros_bag as pb

    stats = pb.read_recording("run.bag")             # RecordingStats, per topic
    system = pb.load_system("system.yaml")           # System (or a model.json)
    entries, _ = pb.find_entries("recordings")       # manifest entries (+ its system path)
    result = pb.characterise(entries, system)        # result.rows, result.failures
    result = pb.build_model("system.yaml", "characterisation.csv")   # fits per node
    pb.write_model("model.json", result.document)
    plan = pb.solve(pb.load_system("model.json"), 1, "greedy")     # Plan
    pb.save_plan(plan, "plan.json")
    check = pb.validate("run.bag", "plan.json")      # eq 10: check.passed, check.to_dict()
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import InfeasibleError, InputError, PerfrosError, PerfrosWarning

if TYPE_CHECKING:  # what the lazy names are, for type checkers and editors
    from perfros_bag.characterisation.table import characterise, find_entries
    from perfros_bag.export.writers import export_plan
    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import read_model, write_model
    from perfros_bag.ingest import read_recording
    from perfros_bag.ingest.stats import RecordingStats, TopicStats
    from perfros_bag.report.html import build_report
    from perfros_bag.solver import solve
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.planfile import load_plan, save_plan
    from perfros_bag.system.systemfile import load_system
    from perfros_bag.system.types import System
    from perfros_bag.validation.eq10 import Validation
    from perfros_bag.validation.eq10 import validate_files as validate

__version__ = "0.1.0"

#: public name -> (module, name there); imported by :func:`__getattr__` on first use.
_LAZY: dict[str, tuple[str, str]] = {
    "read_recording": ("perfros_bag.ingest", "read_recording"),
    "RecordingStats": ("perfros_bag.ingest.stats", "RecordingStats"),
    "TopicStats": ("perfros_bag.ingest.stats", "TopicStats"),
    "load_system": ("perfros_bag.system.systemfile", "load_system"),
    "System": ("perfros_bag.system.types", "System"),
    "load_plan": ("perfros_bag.system.planfile", "load_plan"),
    "save_plan": ("perfros_bag.system.planfile", "save_plan"),
    "Plan": ("perfros_bag.system.plan", "Plan"),
    "find_entries": ("perfros_bag.characterisation.table", "find_entries"),
    "characterise": ("perfros_bag.characterisation.table", "characterise"),
    "build_model": ("perfros_bag.fitting.build", "build_model"),
    "read_model": ("perfros_bag.fitting.modelfile", "read_model"),
    "write_model": ("perfros_bag.fitting.modelfile", "write_model"),
    "solve": ("perfros_bag.solver", "solve"),
    "validate": ("perfros_bag.validation.eq10", "validate_files"),
    "Validation": ("perfros_bag.validation.eq10", "Validation"),
    "export_plan": ("perfros_bag.export.writers", "export_plan"),
    "build_report": ("perfros_bag.report.html", "build_report"),
}

__all__ = [
    "InfeasibleError", "InputError", "PerfrosError", "PerfrosWarning", "Plan", "RecordingStats",
    "System", "TopicStats", "Validation", "__version__", "build_model", "build_report", "characterise",
    "export_plan", "find_entries", "load_plan", "load_system", "read_model", "read_recording",
    "save_plan", "solve", "validate", "write_model",
]


if not TYPE_CHECKING:  # hidden from type checkers, which then flag unknown names

    def __getattr__(name: str) -> Any:
        """Import a public name's module on first use (PEP 562)."""
        try:
            module, attr = _LAZY[name]
        except KeyError:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
        value = getattr(importlib.import_module(module), attr)
        globals()[name] = value  # later lookups skip this function
        return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
