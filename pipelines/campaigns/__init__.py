"""Estimation campaigns: `envisat simulate` (a truth), `envisat estimate` (the batched UKF over one truth), `envisat montecarlo` (its config, blocks, outputs and rate sweep) and `envisat report`."""
