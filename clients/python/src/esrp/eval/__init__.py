"""Evaluation tools, for people who score agents: `evaluation` (`esrp eval`: agents over a split on
one `AsyncClient`, resumable), `ray_eval` (`esrp eval --ray`: the same over a Ray cluster; the `ray`
extra), `results` (the `esrp.results/v1` schema of docs/evaluation.md), `replay` (`esrp replay`: a
record re-run and drawn), `verify` (`esrp verify`: records replayed and checked), `report` (`esrp
report`: tables, plots and stills; the `report` extra), `leaderboard` (`esrp report --leaderboard`),
`signing` (the server records' signatures, checked on a line's bytes), `manifest` (a records
folder's `challenge-scenes.json`) and `_pool` (the worker pool `evaluation` and `verify` run their
episodes in).

Importing this package imports none of them; each needs only the client core and `esrp.agents`.
They use the public client API and read no esrp.v1 message.
"""
