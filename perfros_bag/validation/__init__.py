"""A later run against its plan: eq 10 per node and overall, computer and link loads."""
