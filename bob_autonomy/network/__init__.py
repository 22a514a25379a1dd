"""The network of the paper's agent (body + network + behaviour): the mesh packets every vessel broadcasts, and
their authentication with a fleet key."""
