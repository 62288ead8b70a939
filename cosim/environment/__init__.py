"""The env: pure functions of a `cosim.sumo.snapshot.Snapshot` and the config (`control`, `velocity_map`,
`reward` terms, `episode` endings, `collisions` attribution, the episode `tracker`), the `render`er, the
hand-written `policies`, and the PettingZoo env that steps them in order (`merge_env`)."""
