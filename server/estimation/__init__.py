"""State estimation and dynamics on MuJoCo, with no gRPC and no session in sight: what a session
needs from an estimator (`interface`), its settings (`config`) and state layouts (`layout`), the
factory that picks one (`factory`), the unscented Kalman filter (`ukf`, with `batched`,
`linear_force`, `sigma`, `manifold`, its restart policy `guard`, adaptive noise `adaptive`, the
forecast over gaps `forecast`, the PASSIVE-to-DRIVEN switch `switch`), batched sigma-point
propagation and its worker pool (`propagate`, `pool`), the IEEE 1278 extrapolators
(`deadreckoning`) and inverse/forward dynamics (`dynamics`). It imports only the contract layer
(jitdyn.errors, jitdyn.vocabulary, jitdyn.estimator_settings).
"""
