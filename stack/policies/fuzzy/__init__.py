"""Chang 2020: fuzzy boundary following + arrival-time coordination (FLC_SR or LSTM), PSO-optimised.

Modules: :mod:`.tsk` (eq. 3-6), :mod:`.rbc` (sectors, BF eq. 15-16, supervisor Fig. 5),
:mod:`.mrc` (eq. 1-2, 7-14, decentralised), :mod:`.pso` (eq. 17-18), :mod:`.policy` (the Policy).
"""

from .policy import FuzzyConfig, FuzzyPolicy, hand_set_params, load_params, make_fuzzy, make_fuzzy_lstm

__all__ = ["FuzzyConfig", "FuzzyPolicy", "hand_set_params", "load_params", "make_fuzzy", "make_fuzzy_lstm"]
