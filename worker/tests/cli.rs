//! `xfactor-worker` and its `allreduce-bench`: every flag in `--help` with its default, and bad
//! values refused by the parser naming the flag.

#[path = "../../test-support/help.rs"]
mod help;

const WORKER: &str = env!("CARGO_BIN_EXE_xfactor-worker");

#[test]
fn help_lists_every_flag_with_its_default() {
    help::assert_flags(
        WORKER,
        &[],
        &[
            ("--coordinator", None),
            ("--no-slurm", None),
            ("--token", None),
            ("--token-env", Some("XFACTOR_TOKEN")),
            ("--listen", Some("127.0.0.1:0")),
            ("--advertise", None),
            ("--device", None),
            ("--devices", None),
            ("--activation-checkpointing", None),
            ("--threads", None),
            ("--name", None),
            ("--model-config", None),
            ("--collective-timeout-s", Some("120")),
            ("--shutdown-grace-s", Some("10")),
            ("--kernel-cache", None),
            ("--scratch", None),
            ("--log-format", Some("human")),
            ("--metrics-address", None),
            ("--tls-ca", None),
            ("--tls-domain", None),
            ("--tls-cert", None),
            ("--tls-key", None),
            ("--drill-diverge-from-step", None),
        ],
    );
    help::assert_flags(
        WORKER,
        &["allreduce-bench"],
        &[
            ("--rank", None),
            ("--peers", None),
            ("--sizes-mb", Some("1,16,64,100")),
            ("--repeats", Some("5")),
            ("--threads", Some("1")),
            ("--lanes", Some("1")),
            ("--tls-dir", None),
            ("--chunk-values", None),
        ],
    );
}

#[test]
fn bad_values_are_refused_naming_the_flag() {
    let daemon = ["--coordinator", "http://127.0.0.1:1", "--token", "t"];
    for (bad, flag) in [
        (
            &["--collective-timeout-s", "abc"][..],
            "--collective-timeout-s",
        ),
        (
            &["--collective-timeout-s", "0"][..],
            "--collective-timeout-s",
        ),
        (&["--shutdown-grace-s", "0"][..], "--shutdown-grace-s"),
        (&["--device", "tpu"][..], "--device"),
        (&["--devices", "0,0"][..], "--devices"),
        (&["--threads", "many"][..], "--threads"),
        (&["--log-format", "xml"][..], "--log-format"),
        (
            &["--tls-cert", "c.pem", "--tls-ca", "ca.pem"][..],
            "--tls-key",
        ),
        (&["--tls-domain", "x"][..], "--tls-ca"),
    ] {
        help::assert_refused(WORKER, &[&daemon[..], bad].concat(), flag);
    }
    help::assert_refused(WORKER, &["--token", "t"], "--coordinator");
    let bench = ["allreduce-bench", "--rank", "0", "--peers", "127.0.0.1:1"];
    for (bad, flag) in [
        (&["--threads", "0"][..], "--threads"),
        (&["--sizes-mb", "1,x"][..], "--sizes-mb"),
    ] {
        help::assert_refused(WORKER, &[&bench[..], bad].concat(), flag);
    }
}

#[test]
fn wgpu_on_a_host_without_an_adapter_is_refused_before_the_worker_joins() {
    // No Vulkan driver: the loader is pointed at an ICD file that does not exist.
    let output = std::process::Command::new(WORKER)
        .args(["--coordinator", "http://127.0.0.1:1", "--token", "t"])
        .args(["--device", "wgpu", "--no-slurm"])
        .env("VK_ICD_FILENAMES", "/nonexistent/icd.json")
        .env("VK_DRIVER_FILES", "/nonexistent/icd.json")
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{said}");
    assert!(said.contains("no Vulkan, Metal or DX12 adapter"), "{said}");
}

#[test]
fn a_backend_left_out_of_this_build_is_refused_naming_its_cargo_feature() {
    let backends = [
        ("vulkan", cfg!(feature = "vulkan")),
        ("cuda", cfg!(feature = "cuda")),
        ("libtorch", cfg!(feature = "libtorch")),
    ];
    for (backend, _) in backends.into_iter().filter(|(_, built)| !built) {
        let output = std::process::Command::new(WORKER)
            .args(["--coordinator", "http://127.0.0.1:1", "--token", "t"])
            .args(["--device", backend, "--no-slurm"])
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(1), "{said}");
        assert!(
            said.contains(&format!("built without the `{backend}` cargo feature")),
            "{said}"
        );
        assert!(said.contains(&format!("--features {backend}")), "{said}");
    }
}

#[test]
fn a_missing_token_names_the_variable() {
    let var = "XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET";
    let daemon = ["--coordinator", "http://127.0.0.1:1", "--token-env", var];
    help::assert_fails(WORKER, &daemon, 1, var);
}
