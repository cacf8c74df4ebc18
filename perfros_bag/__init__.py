"""perfros-bag: performance-driven configuration of distributed ROS applications.

The library is importable on its own; ``perfros_bag.cli`` is a thin typer layer over it.
"""

from perfros_bag.errors import InfeasibleError, InputError, PerfrosError, PerfrosWarning

__version__ = "0.1.0"
__all__ = ["InfeasibleError", "InputError", "PerfrosError", "PerfrosWarning", "__version__"]
