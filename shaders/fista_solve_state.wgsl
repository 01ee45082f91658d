// Appended by the hosts of the dense fit's FISTA kernels (fista_step, fista_state,
// fista_restart): the solve's momentum, restart, count and stop on the device
// (gpu::fista_step::State).

struct State {
    t: f32,
    momentum: f32,
    restarted: u32,
    settled: u32,
    steps: u32,
    tolerance: f32,
    // Whether the next step's look-ahead carries momentum (1) or is σ itself (0).
    coasting: u32,
    _pad0: u32,
}
