"""The paper's own workflow (issue 42): a model's own evaluator runs once per cell under `patch_loader`
(`foreign.ladder` says which cells), and its per-cell table goes through the suite's analysis
(`foreign.table` reads it, `foreign.records` turns it into cell records, `report.table_import` writes the
outputs)."""
