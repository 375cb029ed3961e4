"""Grip 2010 (PhD thesis, chapters 1-9): reproductions, sweeps and tuning problems of its examples."""
