"""Runnable examples that re-run the seed material's worked examples with this engine."""
