//! The offline log readers of exocal-report: candump text, CSV samples and MCAP bytes (including
//! truncated MCAP files, as left by a killed daemon) never panic them.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    match which % 3 {
        0 => {
            let _ = exocal_report::readers::read_mcap_frames(rest);
        }
        1 => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = exocal_report::readers::parse_candump(text);
            }
        }
        _ => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = exocal_report::readers::parse_csv(text);
            }
        }
    }
});
