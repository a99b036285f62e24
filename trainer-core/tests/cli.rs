//! `xfactor-check`: its one flag in `--help` with its default, and a bad backend refused by the
//! parser naming the flag.

#[path = "../../test-support/help.rs"]
mod help;

const CHECK: &str = env!("CARGO_BIN_EXE_xfactor-check");

#[test]
fn help_lists_the_backend_flag_with_its_default_and_refuses_a_bad_one() {
    help::assert_flags(CHECK, &[], &[("--backend", Some("cpu"))]);
    help::assert_refused(
        CHECK,
        &["fixture.safetensors", "--backend", "tpu"],
        "--backend",
    );
    help::assert_refused(CHECK, &[], "FIXTURE.safetensors");
}
