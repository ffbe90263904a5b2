"""Data association: gates, assignment (Hungarian, greedy), candidate pairs from a grid, PDA, loopy belief
propagation and the Gibbs sampler of the GLMB."""
