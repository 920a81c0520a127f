"""The numerics of the Kalman family: the fused Kalman step and its whole-record scan
(:mod:`~estim.solvers.kalman.kalman`, open first), the Rauch-Tung-Striebel backward
recursion (:mod:`~estim.solvers.kalman.rts`), and the QR triangularisation, Cholesky
downdates and triangular solves of the square-root forms
(:mod:`~estim.solvers.kalman.triangular`)."""
