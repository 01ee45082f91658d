// dL/dF for render.wgsl without float atomics: the f32 bits in an atomic<u32>, added by a
// compare-exchange loop (retries while another invocation changed the value in between).
@group(0) @binding(5) var<storage, read_write> dense_grad: array<atomic<u32>>;

fn add_grad(i: u32, v: f32) {
    var old = atomicLoad(&dense_grad[i]);
    loop {
        let swapped = atomicCompareExchangeWeak(&dense_grad[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if (swapped.exchanged) {
            break;
        }
        old = swapped.old_value;
    }
}
