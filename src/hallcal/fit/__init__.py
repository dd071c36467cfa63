"""Step 3 of Algorithm 1 and its companions: simulation-error minimization (Fourier and kernel
bases), model-order choice, model adequacy, and the open-loop constant-speed fit."""
