"""Studies behind the metrics' defaults: scripts that print the evidence
(run with ``python -m metrics.studies.<name>``)."""
