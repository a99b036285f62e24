//! `xfactor transfer|evaluate|compare|curve`: every flag in `--help` with its default, and bad values
//! refused by the parser naming the flag.

#[path = "../../test-support/help.rs"]
mod help;

const XFACTOR: &str = env!("CARGO_BIN_EXE_xfactor");

#[test]
fn help_lists_every_flag_with_its_default() {
    help::assert_flags(
        XFACTOR,
        &["transfer"],
        &[
            ("--checkpoint", None),
            ("--trajectory", None),
            ("--scene", None),
            ("--out", None),
            ("--reference", Some("0")),
            ("--frames", None),
            ("--scene-frames", None),
            ("--backend", Some("cpu")),
            ("--log-format", Some("human")),
        ],
    );
    help::assert_flags(
        XFACTOR,
        &["evaluate"],
        &[
            ("--checkpoint", None),
            ("--context-views", Some("1")),
            ("--label", None),
            ("--out", None),
            ("--spec", None),
            ("--oracle", None),
            ("--oracle-command", None),
            ("--oracle-subdivisions", None),
            ("--lpips", None),
            ("--backend", Some("cpu")),
            ("--log-format", Some("human")),
        ],
    );
    help::assert_flags(
        XFACTOR,
        &["compare"],
        &[
            ("--label", None),
            ("--threshold", Some("20")),
            ("--stage", None),
            ("--out", None),
        ],
    );
    help::assert_flags(
        XFACTOR,
        &["curve"],
        &[
            ("--run", None),
            ("--stage", Some("1")),
            ("--spec", None),
            ("--context-views", None),
            ("--out", None),
            ("--backend", Some("cpu")),
            ("--log-format", Some("human")),
        ],
    );
}

#[test]
fn bad_values_are_refused_naming_the_flag() {
    let evaluate = ["evaluate", "--checkpoint", "m.safetensors", "--out", "o"];
    for (bad, flag) in [
        (&["--backend", "tpu"][..], "--backend"),
        (&["--oracle", "colmap"][..], "--oracle"),
        (&["--context-views", "two"][..], "--context-views"),
        (
            &["--oracle", "classical", "--oracle-command", "p"][..],
            "--oracle-command",
        ),
    ] {
        help::assert_refused(XFACTOR, &[&evaluate[..], bad].concat(), flag);
    }
    help::assert_refused(XFACTOR, &["evaluate", "--out", "o"], "--checkpoint");
    for (bad, flag) in [
        (&["--context-views", "1,2,3"][..], "--context-views"),
        (&["--label", "a", "--label", "b"][..], "--label"),
    ] {
        help::assert_fails(XFACTOR, &[&evaluate[..], bad].concat(), 1, flag);
    }
    help::assert_refused(XFACTOR, &["compare", "--out", "o"], "<RUN>");
    help::assert_refused(
        XFACTOR,
        &["compare", "run", "--out", "o", "--threshold", "x"],
        "--threshold",
    );
    help::assert_refused(
        XFACTOR,
        &[
            "transfer",
            "--checkpoint",
            "m",
            "--trajectory",
            "t",
            "--scene",
            "s",
            "--out",
            "o",
            "--reference",
            "first",
        ],
        "--reference",
    );
}
