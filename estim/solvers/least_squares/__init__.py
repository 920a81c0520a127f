"""The least-squares machinery of the window family (full information, MHE, the shooting
observer).

Open first: :mod:`~estim.solvers.least_squares.nlp` (the problem as one NLP: Ipopt, SQP,
fatrop or the structured Gauss-Newton solver), then
:mod:`~estim.solvers.least_squares.gauss_newton` (projected Gauss-Newton on the
block-tridiagonal problem) with its pieces: :mod:`~estim.solvers.least_squares.stages` and
:mod:`~estim.solvers.least_squares.blocks` (the stage functions and their block
factorisation), :mod:`~estim.solvers.least_squares.chunked` (long records in chunks),
:mod:`~estim.solvers.least_squares.globalisation` (line search and trust region),
:mod:`~estim.solvers.least_squares.builders` and :mod:`~estim.solvers.least_squares.options`
(building the NLP and its options), :mod:`~estim.solvers.least_squares.robust` and
:mod:`~estim.solvers.least_squares.reweighting` (robust losses),
:mod:`~estim.solvers.least_squares.rti` (the real-time iteration) and
:mod:`~estim.solvers.least_squares.solution` (what a solve returns).
"""
