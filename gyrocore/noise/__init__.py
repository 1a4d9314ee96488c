"""Noise identification: Allan deviation, GMWM, the random-walk / Gauss-Markov check, bias tracking."""
