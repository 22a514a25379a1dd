"""The swarm's radio: the channel model, the broadcast medium of lockstep runs, mesh security, the UDP relay."""
