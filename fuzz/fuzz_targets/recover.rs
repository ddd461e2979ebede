//! `exocald recover`: arbitrary bytes behind the MCAP magic, and the damaged
//! logs of the seed corpus, rewritten as a complete file. Invariant: what is not MCAP is
//! `NotMcap`; otherwise the output is a finished MCAP that scans whole, holding exactly the
//! messages the recovery counted — never a panic, an abort or an allocation the input claims.
#![no_main]

use std::io::Cursor;

use exocal_log::scan::{scan, End, McapRecord};
use exocal_log::recover::{is_finished, recover, RecoverError};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    match recover(data, Cursor::new(Vec::new()), None) {
        Err(RecoverError::NotMcap) => assert!(!data.starts_with(b"\x89MCAP0\r\n")),
        Err(RecoverError::Write(e)) => panic!("the writer refused what the scan kept: {e}"),
        Ok((recovery, out)) => {
            let out = out.into_inner();
            assert!(is_finished(&out));
            let mut messages = 0u64;
            let again = scan(out.as_slice(), |records| {
                messages += records
                    .iter()
                    .filter(|r| matches!(r, McapRecord::Message { .. }))
                    .count() as u64;
                Ok::<(), ()>(())
            })
            .expect("no callback error");
            assert_eq!(again.end, End::Complete, "{again}");
            assert_eq!(messages, recovery.messages);
        }
    }
});
