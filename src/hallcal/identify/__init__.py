"""Step 2 of Algorithm 1: multisine excitation and the Best Linear Approximation of the plant."""
