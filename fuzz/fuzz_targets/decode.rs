//! Frame decoding: `decode` never panics; whatever decodes re-encodes, and re-decodes to the
//! same identifier; pose pages fed to the assembler never panic it.
#![no_main]

use exocal_dbc::pose::PoseAssembler;
use exocal_dbc::{decode, Message};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|frames: Vec<(u16, Vec<u8>)>| {
    let mut poses = PoseAssembler::new();
    for (id, data) in frames {
        let Ok(msg) = decode(id, &data) else {
            continue;
        };
        let (id2, bytes, dlc) = msg.encode().expect("a decoded message re-encodes");
        assert_eq!(id2, id, "re-encoded identifier differs");
        let again = decode(id2, &bytes[..usize::from(dlc)]).expect("re-encoded frame decodes");
        assert_eq!(again.node(), msg.node());
        if let Message::EePose(page) = msg {
            let _ = poses.push(page);
        }
    }
});
