//! A recording holds what its commands use: a buffer its owner drops lives on until the
//! last recording that uses it is gone, so replaying it is always safe.

mod common;

use vkdr::gpu::{Buffer, BufferKind, Recorder};

#[test]
fn a_recording_keeps_a_dropped_buffer_alive() {
    let ctx = common::context();
    let source = Buffer::from_slice(&ctx, "source", &[1u32, 2, 3, 4]).unwrap();
    let target = Buffer::new(&ctx, "target", 16, BufferKind::Device).unwrap();
    let recording = {
        let scratch = Buffer::new(&ctx, "scratch", 16, BufferKind::Device).unwrap();
        let mut rec = Recorder::new(&ctx).unwrap();
        rec.copy_buffer(&source, 0, &scratch, 0, 16);
        rec.memory_barrier();
        rec.fill_buffer_range(&scratch, 0, 4, 9);
        rec.memory_barrier();
        rec.copy_buffer(&scratch, 0, &target, 0, 16);
        rec.finish().unwrap()
        // The scratch buffer's owner drops it here.
    };
    // Buffers made now would get the scratch buffer's memory, were it freed.
    let decoys: Vec<Buffer> = (0..8u32)
        .map(|i| Buffer::from_slice(&ctx, "decoy", &[0xdead_0000 + i; 4]).unwrap())
        .collect();
    for _ in 0..2 {
        ctx.replay(&recording).unwrap();
        assert_eq!(target.read::<u32>().unwrap(), vec![9, 2, 3, 4]);
    }
    for (i, decoy) in (0u32..).zip(&decoys) {
        assert_eq!(decoy.read::<u32>().unwrap(), vec![0xdead_0000 + i; 4]);
    }
    drop(recording);
    common::assert_no_validation_errors(&ctx);
}
