//! Defaults from a Slurm launch: a worker started by `srun` (see `deploy/slurm/`) finds the
//! coordinator on the job's first node, names itself after the job and its task, listens on
//! every interface and advertises its node's name, with no flags. Explicit flags win, and
//! `--no-slurm` (or `XFACTOR_SLURM=off`) turns the detection off.
//!
//! Read: `SLURM_JOB_ID`, `SLURM_PROCID`, `SLURM_NTASKS`, `SLURM_JOB_NODELIST` (expanded by
//! `scontrol show hostnames`), `SLURMD_NODENAME`, `SLURM_STEP_GPUS`, `SLURM_RESTART_COUNT`.

use std::process::Command;

/// The coordinator's gRPC port on the first node, unless `XFACTOR_COORDINATOR_PORT` says.
pub const DEFAULT_COORDINATOR_PORT: u16 = 50051;

/// Why the Slurm environment could not give the defaults.
#[derive(Debug, thiserror::Error)]
pub enum SlurmError {
    /// `scontrol` is missing or failed.
    #[error(
        "SLURM_JOB_NODELIST={nodelist} could not be expanded with `scontrol show hostnames`: {reason}; pass --coordinator, or --no-slurm"
    )]
    Hostnames {
        /// The compressed node list.
        nodelist: String,
        /// What went wrong.
        reason: String,
    },
    /// A variable holds something else than expected.
    #[error("{variable}={value} is not {expected}")]
    Malformed {
        /// The variable.
        variable: &'static str,
        /// Its value.
        value: String,
        /// What it should be.
        expected: &'static str,
    },
}

/// What a Slurm launch says about this worker.
#[derive(Debug, Clone, PartialEq)]
pub struct SlurmLaunch {
    /// `SLURM_JOB_ID`.
    pub job_id: String,
    /// `SLURM_PROCID`: this task's index.
    pub task: u32,
    /// `SLURM_NTASKS`.
    pub tasks: Option<u32>,
    /// The coordinator on the first node of `SLURM_JOB_NODELIST`.
    pub coordinator: Option<String>,
    /// `SLURMD_NODENAME`: the name peers reach this node by.
    pub node: Option<String>,
    /// `SLURM_STEP_GPUS`: the GPUs given to this step.
    pub gpus: Option<String>,
    /// `SLURM_RESTART_COUNT`: how often the job was requeued.
    pub restarts: u32,
}

impl SlurmLaunch {
    /// The worker's name: `slurm-<job>-<task>`.
    pub fn worker_name(&self) -> String {
        format!("slurm-{}-{}", self.job_id, self.task)
    }
}

/// Whether `XFACTOR_SLURM` turns detection off.
fn switched_off(setting: Option<&str>) -> bool {
    matches!(
        setting.map(str::to_ascii_lowercase).as_deref(),
        Some("off" | "0" | "false" | "no")
    )
}

fn number(variable: &'static str, value: String) -> Result<u32, SlurmError> {
    value.trim().parse().map_err(|_| SlurmError::Malformed {
        variable,
        value,
        expected: "a whole number",
    })
}

/// The launch described by `variable` (the environment), with `hostnames` expanding a node
/// list; `None` outside Slurm or when `XFACTOR_SLURM=off`.
pub fn detect(
    variable: &dyn Fn(&str) -> Option<String>,
    hostnames: &dyn Fn(&str) -> Result<Vec<String>, SlurmError>,
) -> Result<Option<SlurmLaunch>, SlurmError> {
    if switched_off(variable("XFACTOR_SLURM").as_deref()) {
        return Ok(None);
    }
    let Some(job_id) = variable("SLURM_JOB_ID") else {
        return Ok(None);
    };
    let port = match variable("XFACTOR_COORDINATOR_PORT") {
        Some(port) => port
            .trim()
            .parse::<u16>()
            .map_err(|_| SlurmError::Malformed {
                variable: "XFACTOR_COORDINATOR_PORT",
                value: port,
                expected: "a port number",
            })?,
        None => DEFAULT_COORDINATOR_PORT,
    };
    let coordinator =
        match variable("SLURM_JOB_NODELIST") {
            Some(nodelist) => {
                let first = hostnames(&nodelist)?.into_iter().next().ok_or_else(|| {
                    SlurmError::Hostnames {
                        nodelist: nodelist.clone(),
                        reason: "it names no host".into(),
                    }
                })?;
                Some(format!("http://{first}:{port}"))
            }
            None => None,
        };
    Ok(Some(SlurmLaunch {
        job_id,
        task: variable("SLURM_PROCID").map_or(Ok(0), |v| number("SLURM_PROCID", v))?,
        tasks: variable("SLURM_NTASKS")
            .map(|v| number("SLURM_NTASKS", v))
            .transpose()?,
        coordinator,
        node: variable("SLURMD_NODENAME"),
        gpus: variable("SLURM_STEP_GPUS").filter(|gpus| !gpus.is_empty()),
        restarts: variable("SLURM_RESTART_COUNT")
            .map_or(Ok(0), |v| number("SLURM_RESTART_COUNT", v))?,
    }))
}

/// `scontrol show hostnames NODELIST`: the node list expanded, one host per line.
pub fn scontrol_hostnames(nodelist: &str) -> Result<Vec<String>, SlurmError> {
    let failed = |reason: String| SlurmError::Hostnames {
        nodelist: nodelist.into(),
        reason,
    };
    let output = Command::new("scontrol")
        .args(["show", "hostnames", nodelist])
        .output()
        .map_err(|e| failed(format!("scontrol could not run ({e})")))?;
    if !output.status.success() {
        return Err(failed(format!(
            "scontrol exited with {}: {}",
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        )));
    }
    Ok(String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::trim)
        .filter(|line| !line.is_empty())
        .map(String::from)
        .collect())
}

/// The launch of this process: [`detect`] over the real environment and `scontrol`.
pub fn from_environment() -> Result<Option<SlurmLaunch>, SlurmError> {
    detect(&|name| std::env::var(name).ok(), &scontrol_hostnames)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn detect_in(vars: &[(&str, &str)]) -> Result<Option<SlurmLaunch>, SlurmError> {
        let vars: HashMap<String, String> = vars
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect();
        detect(&|name| vars.get(name).cloned(), &|list| {
            assert_eq!(list, "gpu[07-09]");
            Ok(vec!["gpu07".into(), "gpu08".into(), "gpu09".into()])
        })
    }

    #[test]
    fn a_slurm_task_finds_the_coordinator_on_the_first_node_and_names_itself() {
        let launch = detect_in(&[
            ("SLURM_JOB_ID", "4242"),
            ("SLURM_PROCID", "2"),
            ("SLURM_NTASKS", "3"),
            ("SLURM_JOB_NODELIST", "gpu[07-09]"),
            ("SLURMD_NODENAME", "gpu09"),
            ("SLURM_STEP_GPUS", "0,1,2,3"),
            ("SLURM_RESTART_COUNT", "1"),
        ])
        .unwrap()
        .unwrap();
        assert_eq!(launch.coordinator.as_deref(), Some("http://gpu07:50051"));
        assert_eq!(launch.worker_name(), "slurm-4242-2");
        assert_eq!(launch.tasks, Some(3));
        assert_eq!(launch.node.as_deref(), Some("gpu09"));
        assert_eq!(launch.gpus.as_deref(), Some("0,1,2,3"));
        assert_eq!(launch.restarts, 1);
    }

    #[test]
    fn outside_slurm_or_switched_off_there_is_no_launch() {
        assert_eq!(detect_in(&[]).unwrap(), None);
        for off in ["off", "OFF", "0", "false"] {
            let vars = [("SLURM_JOB_ID", "1"), ("XFACTOR_SLURM", off)];
            assert_eq!(detect_in(&vars).unwrap(), None, "{off}");
        }
    }

    #[test]
    fn the_port_can_be_moved_and_bad_values_are_named() {
        let launch = detect_in(&[
            ("SLURM_JOB_ID", "1"),
            ("SLURM_JOB_NODELIST", "gpu[07-09]"),
            ("XFACTOR_COORDINATOR_PORT", "6000"),
        ])
        .unwrap()
        .unwrap();
        assert_eq!(launch.coordinator.as_deref(), Some("http://gpu07:6000"));
        let error = detect_in(&[("SLURM_JOB_ID", "1"), ("SLURM_PROCID", "two")]).unwrap_err();
        assert_eq!(error.to_string(), "SLURM_PROCID=two is not a whole number");
    }

    #[test]
    fn a_node_list_that_cannot_be_expanded_says_what_to_do() {
        let vars: HashMap<&str, &str> =
            [("SLURM_JOB_ID", "1"), ("SLURM_JOB_NODELIST", "n[1-2]")].into();
        let error = detect(&|name| vars.get(name).map(|v| v.to_string()), &|list| {
            Err(SlurmError::Hostnames {
                nodelist: list.into(),
                reason: "scontrol could not run (not found)".into(),
            })
        })
        .unwrap_err();
        let message = error.to_string();
        assert!(message.contains("SLURM_JOB_NODELIST=n[1-2]"), "{message}");
        assert!(message.contains("--no-slurm"), "{message}");
    }
}
