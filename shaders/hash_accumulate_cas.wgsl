// Gradient accumulation on any device: the f32 is kept as its bits in an
// atomic<u32> and added with a compare-and-swap loop, retried until no other
// invocation wrote the entry in between. Exact f32 additions, like the
// native atomics; only the order varies. The kernel that appends it
// declares `d_params: array<GradientCell>` at its own binding.

alias GradientCell = atomic<u32>;

fn add_gradient(i: u32, value: f32) {
    var old = atomicLoad(&d_params[i]);
    loop {
        let new_bits = bitcast<u32>(bitcast<f32>(old) + value);
        let result = atomicCompareExchangeWeak(&d_params[i], old, new_bits);
        if (result.exchanged) {
            break;
        }
        old = result.old_value;
    }
}
