"""Scoring: statistics over finished cells, as pure functions over plain data.

`records` holds a cell's summary and the run's typed analysis (axes, verdict, thresholds, null control, floor);
`retention` the retention, its paired bootstrap and the thresholds; `intervals` the joint bootstrap; `verdict` the
axes, the label and the controls; `analyse` puts them together in `analyse_run`; `baseline` the CI gate. How one
plan is scored lives in `metrics/`; the ego-only floor in `floor.py`. Nothing here imports pytest.
"""
