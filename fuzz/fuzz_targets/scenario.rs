//! The hil scenario parser (TOML plus `validate`): arbitrary text never panics it.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|text: &str| {
    if let Ok(s) = exocal_hil::Scenario::from_toml(text) {
        let _ = s.validate();
    }
});
