"""The number of Newton steps of P2's flexed-beam solves (:mod:`.shaft`'s numpy functions and their compiled
twins in :mod:`.compiled`, which must take the same steps to give the same bits). The lowest module of the
kinematics: it imports nothing."""

NEWTON_ITERS = 8
