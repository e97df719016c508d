"""How one plan is scored against its frame: `trajectory` (L2, collisions, jerk, bit density, conventions) and
`pdms/` (the PDMS-like rule-based score: constants, motion, agents, the rules, the reference and the prepared
form). Used while a cell runs; nothing here imports pytest."""
