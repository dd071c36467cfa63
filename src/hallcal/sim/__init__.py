"""Simulation: transfer functions with exact ZOH discretization, the closed loop of eq. (state_eq)
with its exact parameter sensitivities, and the virtual bench."""
