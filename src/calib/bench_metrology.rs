//! PURE: the closed-loop simulated metrology benchmark.
