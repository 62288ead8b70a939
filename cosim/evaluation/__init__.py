"""Evaluation, downstream of the env and the agents and importing neither back: `runner` (`cosim evaluate`:
episodes of a policy on evaluation seeds), `stats` (intervals with scipy, summaries, tables), `store` (an
evaluation folder on disk), `plots`, `compare` (`cosim compare`) and `report` (the sweep's report)."""
