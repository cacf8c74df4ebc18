"""The case study's computers as cgroups: the implementation is :mod:`perfros_bag.rosrun.cgroups`."""

from perfros_bag.rosrun.cgroups import (
    CGROUP_ROOT,
    PREFIX,
    CpuGroups,
    cgroup_version,
    leftover_groups,
)

__all__ = ["CGROUP_ROOT", "PREFIX", "CpuGroups", "cgroup_version", "leftover_groups"]
