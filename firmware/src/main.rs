//! The orbit-nerf core on an emulated Cortex-M4F (QEMU `mps2-an386`): restores a trained
//! field from the render pack in flash into a render-only arena, renders one view ([`pack::CAMERA`] at [`pack::pose`])
//! and prints the image's fingerprint and the render time over semihosting, then exits QEMU.
//! The host renders the same view from the same pack and prints its fingerprint
//! (`examples/onboard_pack.rs`); scripts/onboard.sh compares the two.
#![no_std]
#![no_main]

mod pack;

use core::ptr::addr_of_mut;
use cortex_m::peripheral::{DWT, SYST, syst::SystClkSource};
use cortex_m_rt::{entry, exception};
use cortex_m_semihosting::{debug, hprintln};
use orbit_nerf_core::{MemoryPlan, Sequential, Trainer};
use panic_semihosting as _;

/// Written by the host (`cargo run --example onboard_pack`) before this crate is built.
static PACK: &[u8] = include_bytes!("../pack/render.pack");

const PLAN: MemoryPlan = MemoryPlan::render_only(&pack::CONFIG);
const PIXELS: usize = pack::CAMERA.width as usize * pack::CAMERA.height as usize;

/// The core's render-only arena, sized at compile time from its memory plan (in .bss).
static mut ARENA: [u8; PLAN.total] = [0; PLAN.total];
static mut IMAGE: [f32; PIXELS * 3] = [0.0; PIXELS * 3];

/// SysTick wraps (every 2^24 ticks of the 25 MHz board clock).
static mut SYSTICK_WRAPS: u32 = 0;

#[exception]
fn SysTick() {
    // SAFETY: only this handler writes the counter; main reads it with SysTick stopped.
    unsafe { SYSTICK_WRAPS += 1 };
}

#[entry]
fn main() -> ! {
    let code = match run() {
        Ok(()) => debug::EXIT_SUCCESS,
        Err(message) => {
            hprintln!("error: {}", message);
            debug::EXIT_FAILURE
        }
    };
    debug::exit(code);
    // Only reached if the debugger ignores the exit request.
    loop {
        cortex_m::asm::wfi();
    }
}

fn run() -> Result<(), &'static str> {
    let mut core = cortex_m::Peripherals::take().ok_or("peripherals taken twice")?;
    // SAFETY: `run` is called once, so these are the only references to the statics.
    let (arena, image) = unsafe { (&mut *addr_of_mut!(ARENA), &mut *addr_of_mut!(IMAGE)) };
    let mut trainer =
        Trainer::new_render_only(pack::CONFIG, arena).map_err(|_| "config or arena refused")?;
    let sections = pack::sections(PACK).ok_or("the flash holds no render pack")?;
    for (name, bytes) in pack::SECTIONS.iter().zip(sections) {
        trainer
            .restore_section(name, bytes)
            .map_err(|_| "a pack section does not fit the config")?;
    }

    core.DCB.enable_trace();
    DWT::unlock();
    core.DWT.enable_cycle_counter();
    core.DWT.set_cycle_count(0);
    core.SYST.set_clock_source(SystClkSource::Core);
    core.SYST.set_reload(0x00ff_ffff);
    core.SYST.clear_current();
    core.SYST.enable_interrupt();
    core.SYST.enable_counter();

    let samples = trainer
        .render(&Sequential, &pack::CAMERA, &pack::pose(), &[], image)
        .map_err(|_| "render refused the view")?;

    core.SYST.disable_counter();
    let cycles = DWT::cycle_count();
    // SAFETY: SysTick is stopped, so its handler no longer runs.
    let wraps = unsafe { *addr_of_mut!(SYSTICK_WRAPS) };
    let ticks = u64::from(wraps) * (1 << 24) + u64::from(0x00ff_ffff - SYST::get_current());

    hprintln!(
        "cortex-m4f render: {}x{} px, {} samples/ray, fnv1a {:#018x}",
        pack::CAMERA.width,
        pack::CAMERA.height,
        samples,
        pack::fnv1a(image)
    );
    hprintln!(
        "arena {} bytes; render: {} SysTick cycles (emulated clock), DWT CYCCNT {}",
        PLAN.total,
        ticks,
        if cycles == 0 {
            "not counted by this machine"
        } else {
            "counted"
        }
    );
    if cycles != 0 {
        hprintln!("DWT cycles: {}", cycles);
    }
    Ok(())
}
