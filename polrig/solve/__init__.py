"""Layer 4, solve: from calibrated frames to Mueller matrices and their scores.

Radiometry of one polarizer state (``radiometry``), the N-state reference solve with its
compiled kernel (``reference``), scoring against simulated truth (``scoring``) and fast tail
percentiles (``quantiles``). Imports the layers below and nothing above.
"""
