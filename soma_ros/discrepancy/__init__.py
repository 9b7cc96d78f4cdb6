"""The discrepancy workflow (`soma discrepancy`): find where the model and measured data
disagree, name the missing effect, add it and show the gap shrink.

* :mod:`.workflow` -- detection, candidate ranking, fitting and the re-fit;
* :mod:`.report` -- its plots and markdown report.
"""
