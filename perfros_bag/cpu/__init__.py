"""CPU traces: ``record`` samples processes with psutil into a ``<stem>.cpu.csv`` trace,
``trace`` reads one back as CPU units per node."""
