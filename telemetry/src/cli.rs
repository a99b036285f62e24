//! Small helpers the workspace's binaries share: flag parsing with errors that name the flag, and logging
//! set-up (human or JSON).

use std::collections::BTreeMap;

/// Flags of a command line: `--name value` pairs and bare `--switch`es.
#[derive(Debug, Default)]
pub struct Flags {
    values: BTreeMap<String, String>,
    switches: Vec<String>,
}

impl Flags {
    /// Parses `args`; `switches` lists the flags that take no value.
    pub fn parse(args: &[String], switches: &[&str], known: &[&str]) -> Result<Self, String> {
        let mut flags = Self::default();
        let mut iter = args.iter();
        while let Some(arg) = iter.next() {
            let Some(name) = arg.strip_prefix("--") else {
                return Err(format!("unexpected argument `{arg}`"));
            };
            if switches.contains(&name) {
                flags.switches.push(name.to_string());
            } else if known.contains(&name) {
                let value = iter
                    .next()
                    .ok_or_else(|| format!("--{name} needs a value"))?;
                flags.values.insert(name.to_string(), value.clone());
            } else {
                return Err(format!(
                    "unknown flag --{name}; known: {}",
                    known
                        .iter()
                        .chain(switches)
                        .map(|f| format!("--{f}"))
                        .collect::<Vec<_>>()
                        .join(" ")
                ));
            }
        }
        Ok(flags)
    }

    /// The value of `--name`, if given.
    pub fn get(&self, name: &str) -> Option<&str> {
        self.values.get(name).map(String::as_str)
    }

    /// The value of `--name`, or an error saying it is required.
    pub fn require(&self, name: &str) -> Result<&str, String> {
        self.get(name)
            .ok_or_else(|| format!("--{name} is required"))
    }

    /// Whether the switch `--name` was given.
    pub fn has(&self, name: &str) -> bool {
        self.switches.iter().any(|s| s == name)
    }
}

/// Logs to stderr, `RUST_LOG`-filtered (default `info`), as text or one JSON object per line.
pub fn init_logging(format: Option<&str>) -> Result<(), String> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    let result = match format.unwrap_or("human") {
        "human" => builder.try_init(),
        "json" => builder.json().try_init(),
        other => return Err(format!("--log-format `{other}`: expected human or json")),
    };
    result.map_err(|e| e.to_string())
}
