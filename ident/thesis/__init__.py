"""The thesis' identification studies as library code (Tayamon 2012, Papers III and IV), run by the experiments.

* :mod:`ident.thesis.paper3` -- Paper III: RPEM on a 2nd-order chain, Euler against midpoint, linear against
  nonlinear regressors, term selection, the repetition over independent segments;
* :mod:`ident.thesis.paper4` -- Paper IV: linear, Wiener and Hammerstein-Wiener models of the tailpipe NOx (M-I..M-V);
* :mod:`ident.thesis.multisegment` -- Paper IV's comparison over many segments, and the NH3 slip as a second output;
* :mod:`ident.thesis.stats` -- robust summaries and paired verdicts of validation FIT over segments.
"""
