"""Control: the velocity controllers (MPC and proportional) of buoys, motorboats and eBots, and the physical
models they plan with."""
