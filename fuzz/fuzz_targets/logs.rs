//! The offline log readers of exocal-report: candump text, CSV samples and MCAP bytes (including
//! truncated MCAP files, as left by a killed daemon) never panic them; nor do they panic the
//! daemon's recovery of a cut log (`exocald::recover`), whose output is always a finished MCAP
//! the reader takes.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&which, rest)) = data.split_first() else {
        return;
    };
    match which % 4 {
        0 => {
            let _ = exocal_report::readers::read_mcap_frames(rest);
        }
        1 => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = exocal_report::readers::parse_candump(text);
            }
        }
        2 => {
            if let Ok(text) = std::str::from_utf8(rest) {
                let _ = exocal_report::readers::parse_csv(text);
            }
        }
        _ => {
            // Behind the magic, so the fuzzer spends its time on the records.
            let bytes = [b"\x89MCAP0\r\n".as_slice(), rest].concat();
            let (_, out) =
                exocald::recover::recover_in_memory(&bytes).expect("starts with the magic");
            assert!(exocald::recover::is_finished(&out));
            let _ = exocal_report::readers::read_mcap_frames(&out);
        }
    }
});
