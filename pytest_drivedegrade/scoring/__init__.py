"""Scoring: every number of the certificate, as pure functions over plain data.

`metrics` scores one plan against its frame (used while a cell runs); `pdms` its PDMS-like safety score;
`records` holds a cell's summary and the run's analysis; `retention` the retention, its paired bootstrap and the
thresholds; `verdict` the axes, the label and `analyse_run`; `baseline` the CI gate; `floor` the ego-only
floor. Nothing here imports pytest.
"""
