"""SUMO networks of the toolkit: `sumo_net.build` generates the on-ramp merge net and `sumo_net.shapes` its usual
shapes; `sumo_net/dilemma/` holds the default one (`cosim.config.DEFAULT_NET`), `sumo_net/merge/` the builder's
default geometry."""
