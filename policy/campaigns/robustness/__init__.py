"""Controllers over the uncertainty envelope (`tools/robustness.py`, docs/robustness.md): the
arms and their episodes (`arms`), one controller's campaign over them (`campaign`), their
identification through the driver (`identification`), the summary's statistics (`summary`),
its docs blocks and console lines (`report`), the progress log (`progress`) and what the
command does with its options (`command`)."""
