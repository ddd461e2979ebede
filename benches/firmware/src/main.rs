//! Firmware-like user of calib-core's least-squares path on a Cortex-M4F.
//!
//! At reset it simulates the paper's Section 4 scenario into a static buffer of [`K`] samples
//! (one every 0.1 s, so 20 s of motion, with drift), paints the free stack, runs
//! `identify_ls::<7, 28>` from the nominal Table 1, and reports over semihosting one line
//!
//! ```text
//! FIRMWARE ok k=200 iterations=12 rank=28 cost_bits=0x3f... stack_used=NNNN stack_painted=NNNN
//! ```
//!
//! then exits QEMU (`cargo xtask bench` parses the line). `stack_used` is the high-water mark of
//! the whole stack since reset (from `_stack_start`, the initial stack pointer, down to the
//! lowest word the LS call overwrote), in bytes: `main`'s own frame (where `identify_ls` and its
//! buffers are inlined) included. `stack_painted` is how far down the paint reached; if
//! `stack_used` equals it, the stack ran into .bss and the figure is only a lower bound.
//! The cost is printed as its IEEE bits so no float formatting code is linked in.
#![no_std]
#![no_main]

use calib_core::{
    identify_ls, DhTable, Frame, LsOptions, Sample, Scenario, ScenarioConfig, SUIT_PARAMS,
};
use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use nalgebra::{Matrix3, Vector3};
use panic_halt as _;

/// Samples in the static dataset.
const K: usize = 200;

const EMPTY: Sample<7> = Sample {
    joints: [0.0; 7],
    pose: Frame {
        r: Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        p: Vector3::new(0.0, 0.0, 0.0),
    },
};

#[entry]
fn main() -> ! {
    // cortex-m-rt turns this into a `&'static mut` to a buffer in .bss.
    static mut SAMPLES: [Sample<7>; K] = [EMPTY; K];
    let samples: &'static mut [Sample<7>; K] = SAMPLES;
    for (slot, s) in samples
        .iter_mut()
        .zip(Scenario::new(ScenarioConfig::paper(), 1).step_by(10))
    {
        *slot = s.sample;
    }
    let painted = stack::paint();
    let result =
        identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), samples, &LsOptions::paper());
    let used = stack::used(&painted);
    match result {
        Ok(r) => {
            hprintln!(
                "FIRMWARE ok k={} iterations={} rank={} cost_bits={:#x} stack_used={} stack_painted={}",
                K,
                r.iterations,
                r.rank,
                r.cost.to_bits(),
                used,
                painted.bytes()
            );
            debug::exit(debug::EXIT_SUCCESS);
        }
        Err(_) => {
            hprintln!("FIRMWARE err stack_used={}", used);
            debug::exit(debug::EXIT_FAILURE);
        }
    }
    loop {
        cortex_m::asm::wfi();
    }
}

/// Stack painting: fill the unused stack with a pattern, later find the lowest overwritten word.
mod stack {
    const PATTERN: u32 = 0x5AC3_5AC3;
    /// Bytes below the painting function's stack pointer left unpainted (its own frame and
    /// whatever an interrupt could push).
    const MARGIN: usize = 256;

    extern "C" {
        /// End of .bss (cortex-m-rt's linker script): the stack may grow down to here.
        static __ebss: u32;
        /// The initial stack pointer (top of RAM).
        static _stack_start: u32;
    }

    /// The painted region `[bottom, painted_top)` and the stack's origin `top`.
    pub struct Painted {
        bottom: usize,
        painted_top: usize,
        top: usize,
    }

    impl Painted {
        /// Depth (bytes below the stack's origin) down to which the stack was painted.
        pub fn bytes(&self) -> usize {
            self.top - self.bottom
        }
    }

    #[inline(never)]
    pub fn paint() -> Painted {
        let sp = cortex_m::register::msp::read() as usize;
        // Taking the address of the linker symbol needs no `unsafe`.
        let bottom = (core::ptr::addr_of!(__ebss) as usize + 3) & !3;
        let top = (sp - MARGIN) & !3;
        let mut p = bottom;
        while p < top {
            // SAFETY: [bottom, top) is RAM between the end of .bss and below the live stack.
            unsafe { core::ptr::write_volatile(p as *mut u32, PATTERN) };
            p += 4;
        }
        Painted {
            bottom,
            painted_top: top,
            top: core::ptr::addr_of!(_stack_start) as usize,
        }
    }

    /// Peak stack depth since reset (bytes below the stack's origin), as seen after [`paint`].
    #[inline(never)]
    pub fn used(painted: &Painted) -> usize {
        let mut p = painted.bottom;
        // SAFETY: reads the region painted by `paint`.
        while p < painted.painted_top
            && unsafe { core::ptr::read_volatile(p as *const u32) } == PATTERN
        {
            p += 4;
        }
        painted.top - p
    }
}
