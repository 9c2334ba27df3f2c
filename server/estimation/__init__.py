"""State estimation and dynamics on MuJoCo, with no gRPC and no session in sight: the estimator
interface and its settings (`estimator`), the factory that picks one (`factory`), the unscented
Kalman filter (`ukf`, `sigma`, `manifold`), batched sigma-point propagation and its worker pool
(`propagate`, `pool`), the IEEE 1278 extrapolators (`deadreckoning`) and inverse/forward dynamics
(`dynamics`). It imports only jitdyn.errors.
"""
