"""The sensor side: f_init (Clarke + atan2 + unwrap), flux models g_theta, the lookup table
f_star and the angle-error metrics (steps 1, 4 and 5 of Algorithm 1, no closed loop involved)."""
