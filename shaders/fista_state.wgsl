// After each FISTA step of the dense fit (mirrors CpuFista::solve between its passes): one
// workgroup adds fista_step.wgsl's partial sums in a fixed order, then restarts the momentum
// when it pointed uphill, sets the next step's momentum, counts the step and marks the solve
// settled once a step whose look-ahead carried momentum changed σ by at most `tolerance` of its
// norm.

struct Partials {
    // Workgroups of fista_step (three sums each).
    count: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> u: Partials;
@group(0) @binding(1) var<storage, read> partials: array<f32>;
@group(0) @binding(2) var<storage, read_write> state: State;

var<workgroup> lanes: array<vec3<f32>, 64>;

fn next_t(t: f32) -> f32 {
    return (1.0 + sqrt(1.0 + 4.0 * t * t)) / 2.0;
}

@compute @workgroup_size(64)
fn main(@builtin(local_invocation_index) lane: u32) {
    var sum = vec3<f32>(0.0);
    for (var g = lane; g < u.count; g += 64u) {
        sum += vec3<f32>(partials[3u * g], partials[3u * g + 1u], partials[3u * g + 2u]);
    }
    lanes[lane] = sum;
    for (var half = 32u; half > 0u; half /= 2u) {
        workgroupBarrier();
        if (lane < half) {
            lanes[lane] += lanes[lane + half];
        }
    }
    if (lane != 0u || state.settled != 0u) {
        return;
    }
    let total = lanes[0];
    // Only a step whose look-ahead carried momentum may end the solve (CpuFista::solve says why).
    let coasted = state.coasting;
    state.steps += 1u;
    var t = next_t(state.t);
    state.restarted = 0u;
    state.coasting = select(0u, 1u, state.momentum > 0.0);
    if (total.z > 0.0) {
        // Adaptive restart: fista_restart.wgsl puts the look-ahead back on σ.
        t = 1.0;
        state.restarted = 1u;
        state.coasting = 0u;
    }
    state.t = t;
    state.momentum = (t - 1.0) / next_t(t);
    if (coasted != 0u && sqrt(total.x / max(total.y, 1e-30)) <= state.tolerance) {
        state.settled = 1u;
    }
}
