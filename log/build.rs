//! Compiles `proto/exocal.proto` (pure Rust: protox, no protoc) into the message types (prost)
//! and the FileDescriptorSet the log's schemas carry.

use prost::Message as _;

fn main() {
    println!("cargo:rerun-if-changed=proto/exocal.proto");
    let fds = protox::compile(["exocal.proto"], ["proto"]).expect("proto/exocal.proto compiles");
    let out = std::path::PathBuf::from(std::env::var_os("OUT_DIR").expect("OUT_DIR"));
    std::fs::write(out.join("exocal.bin"), fds.encode_to_vec()).expect("write exocal.bin");
    prost_build::Config::new()
        // The collection end is also read from the JSON logs written before the log was binary.
        .type_attribute(
            ".exocal.CollectionEnd",
            "#[derive(serde::Serialize, serde::Deserialize)]",
        )
        .type_attribute(
            ".exocal.RejectRun",
            "#[derive(serde::Serialize, serde::Deserialize)]",
        )
        .type_attribute(
            ".exocal.StreamVerification",
            "#[derive(serde::Serialize, serde::Deserialize)]",
        )
        .compile_fds(fds)
        .expect("generate the message types");
}
