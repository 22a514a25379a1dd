"""Experiments: scenario files and their schema, metrics, figures, runs, sweeps and the paper's reproduction."""
