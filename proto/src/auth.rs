//! Where a process finds the job token: the `--token` / `--token-env` flags every client binary
//! shares, and the environment look-up the coordinator's `auth.token_env` uses too.

/// The variable `--token-env` names when neither flag is given.
pub const DEFAULT_TOKEN_ENV: &str = "XFACTOR_TOKEN";

/// Why a token cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TokenError {
    /// HTTP headers carry visible ASCII only.
    #[error("the job token must be visible ASCII without spaces at the ends")]
    NotAscii,
    /// The variable meant to hold the token is unset or not Unicode.
    #[error("cannot read the job token from the environment variable `{var}`")]
    Env {
        /// The variable.
        var: String,
        /// Why it cannot be read.
        #[source]
        source: std::env::VarError,
    },
    /// The token is empty: every request would carry a guessable `Bearer `.
    #[error("the job token from {origin} is empty")]
    Empty {
        /// `--token` or the variable's name.
        origin: String,
    },
}

/// The job token from the environment variable `var`; the error names the variable.
pub fn token_from_env(var: &str) -> Result<String, TokenError> {
    let token = std::env::var(var).map_err(|source| TokenError::Env {
        var: var.to_string(),
        source,
    })?;
    non_empty(token, format!("`{var}`"))
}

fn non_empty(token: String, origin: String) -> Result<String, TokenError> {
    if token.is_empty() {
        Err(TokenError::Empty { origin })
    } else {
        Ok(token)
    }
}

/// The job-token flags. The token is read from an environment variable unless `--token` is
/// given; that variable is `XFACTOR_TOKEN` unless `--token-env` names another. There is no
/// `env =` on `--token` itself: an environment-supplied `--token` would silently win over an
/// explicit `--token-env`, and clap would print its value in `--help`.
#[derive(Debug, Clone, PartialEq, Eq, clap::Args)]
pub struct TokenArgs {
    /// The job token itself (visible to other local users in the process list: prefer --token-env)
    #[arg(long, value_name = "TOKEN")]
    pub token: Option<String>,
    /// Environment variable holding the job token, read when --token is not given
    #[arg(long, value_name = "VAR", default_value = DEFAULT_TOKEN_ENV)]
    pub token_env: String,
}

impl TokenArgs {
    /// The token: `--token`, else the variable `--token-env` names.
    pub fn resolve(&self) -> Result<String, TokenError> {
        match &self.token {
            Some(token) => non_empty(token.clone(), "--token".into()),
            None => token_from_env(&self.token_env),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Cli {
        #[command(flatten)]
        token: TokenArgs,
    }

    fn parse(args: &[&str]) -> TokenArgs {
        Cli::try_parse_from(std::iter::once("test").chain(args.iter().copied()))
            .unwrap()
            .token
    }

    #[test]
    fn the_flag_wins_over_the_variable() {
        let args = parse(&["--token", "abc", "--token-env", "PATH"]);
        assert_eq!(args.resolve().unwrap(), "abc");
    }

    #[test]
    fn the_named_variable_is_read_and_xfactor_token_is_the_default() {
        assert_eq!(parse(&[]).token_env, "XFACTOR_TOKEN");
        let path = std::env::var("PATH").unwrap();
        assert_eq!(parse(&["--token-env", "PATH"]).resolve().unwrap(), path);
    }

    #[test]
    fn an_unset_variable_or_an_empty_token_is_named() {
        let unset = parse(&["--token-env", "XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET"])
            .resolve()
            .unwrap_err();
        assert!(
            matches!(&unset, TokenError::Env { var, .. } if var == "XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET"),
            "{unset:?}"
        );
        assert!(
            unset
                .to_string()
                .contains("XFACTOR_TEST_TOKEN_THAT_IS_NOT_SET")
        );
        let empty = parse(&["--token", ""]).resolve().unwrap_err();
        assert_eq!(empty.to_string(), "the job token from --token is empty");
    }
}
