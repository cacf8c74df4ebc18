"""A later run against its plan: eq 10 per node and overall, computer and link loads."""

#: Largest overall deviation (%) that still passes; here, not in ``eq10``, so that
#: ``validate --help`` can show it without importing the checker.
DEFAULT_TOLERANCE = 5.0
