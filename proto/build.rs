//! Compiles `proto/xfactor.proto` with protox (a protobuf compiler written in Rust), so no
//! `protoc` is needed on the build machine, then generates prost messages and tonic services.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto/xfactor.proto");
    let descriptors = protox::compile(["xfactor.proto"], ["proto"])?;
    tonic_prost_build::configure()
        .bytes(".xfactor.v1.Chunk.values")
        .compile_fds(descriptors)?;
    Ok(())
}
