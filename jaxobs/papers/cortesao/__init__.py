"""Cortesão 2006, Cortesão, Koeppe, Nunes & Hirzinger (stochastic AOBs) and Cortesão's MRAC chapter: the Kalman
Active Observer papers' examples, sweeps and tuning problems."""
