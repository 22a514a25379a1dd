"""The agent core: body + network + behaviour, the clock, the neighbour table and its plausibility checks, the
local frame, the behaviour choice."""
