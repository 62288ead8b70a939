"""SUMO networks of the toolkit: `sumo_net.build` generates the on-ramp merge net; `sumo_net/merge/` holds
the default one."""
