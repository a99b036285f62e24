//! Logging set-up every binary shares: `RUST_LOG`-filtered lines on stderr, as text or JSON,
//! chosen by `--log-format`.

/// How log lines are written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// Text for people, coloured on a terminal.
    #[default]
    Human,
    /// One JSON object per line, for log collectors.
    Json,
}

/// The `--log-format` flag (also read from `XFACTOR_LOG_FORMAT`, so one setting in a unit's or
/// pod's environment covers every process it starts).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::Args)]
pub struct LogArgs {
    /// How log lines are written to stderr (RUST_LOG filters them; default level info)
    #[arg(
        long,
        value_enum,
        value_name = "FORMAT",
        default_value_t = LogFormat::Human,
        env = "XFACTOR_LOG_FORMAT"
    )]
    pub log_format: LogFormat,
}

impl LogArgs {
    /// Starts logging as the flag asks; see [`init_logging`].
    pub fn init(&self) -> Result<(), LoggingError> {
        init_logging(self.log_format)
    }
}

/// Logging could not start (a subscriber is already set in this process).
#[derive(Debug, thiserror::Error)]
#[error("cannot start logging")]
pub struct LoggingError(#[source] Box<dyn std::error::Error + Send + Sync>);

/// Logs to stderr, `RUST_LOG`-filtered (default `info`), in `format`.
pub fn init_logging(format: LogFormat) -> Result<(), LoggingError> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Human => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    }
    .map_err(LoggingError)
}

/// `error` and every cause below it, joined with `: `, for log fields and messages that
/// travel as one string.
pub fn chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut cause = error.source();
    while let Some(next) = cause {
        text.push_str(": ");
        text.push_str(&next.to_string());
        cause = next.source();
    }
    text
}
