//! Settings of `serve` and `worker` in layers: built-in defaults, then a TOML file
//! (`--config FILE`), then the environment (`POINTFARM_*`), then the flags. The file has a
//! `[serve]` and a `[worker]` table whose keys are the commands' long flags with `_` for `-`
//! (`data_dir = "/srv/pointfarm"`, `data_root = ["/scans"]`). Its values become the flags'
//! defaults, so they pass through the flags' own parsers: each setting's range is checked in
//! one place whichever layer gave it, and an error names the file and the key.
//! `--print-config` shows the result, with the layer each value came from.
//!
//! A setting that takes a table of its own (`[[serve.webhook]]`) reaches its flag as the table
//! in TOML's inline form, which the flag's reader parses again ([`webhook_endpoints`]).

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::parser::ValueSource;
use clap::{Arg, ArgAction, ArgMatches, Args, Command, Parser};
use pointfarm_daemon::webhooks::{WebhookEndpoint, WebhookSpec};

/// The commands whose settings a file holds, each in the table of its name.
const LAYERED_COMMANDS: [&str; 2] = ["serve", "worker"];

/// The flags of a layered command that are about its settings rather than settings.
#[derive(Args, Clone, Debug, Default)]
pub struct ConfigArgs {
    /// Read settings from this TOML file (its `[serve]` and `[worker]` tables, keyed by the
    /// long flags with `_` for `-`); the environment and the flags override it.
    #[arg(long, value_name = "FILE", env = "POINTFARM_CONFIG")]
    config: Option<PathBuf>,
    /// Print the settings this command would run with, as TOML with the layer of each
    /// (default, file, env, flag), and exit.
    #[arg(long)]
    print_config: bool,
}

/// Not settings: never read from a file, never printed.
const NOT_SETTINGS: [&str; 4] = ["config", "print_config", "help", "supervised"];

/// Parses `args` as `C`'s command line, with the configuration file's layer under the
/// environment for `serve` and `worker`; exits with clap's message on a bad flag, and with
/// the file's and the key's names on a bad file. `--print-config` prints and exits here.
pub fn parse<C: Parser>(args: Vec<OsString>) -> C {
    let command = C::command();
    let first = command.clone().get_matches_from(args.clone());
    let matches = match layered(command, &first) {
        Ok(Some((command, from_file))) => {
            let matches = command.get_matches_from(args);
            print_config_and_exit(&C::command(), &matches, &from_file);
            matches
        }
        Ok(None) => {
            print_config_and_exit(&C::command(), &first, &[]);
            first
        }
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::exit(2);
        }
    };
    C::from_arg_matches(&matches).unwrap_or_else(|e| e.exit())
}

/// The command with the file's values as the defaults of its layered subcommand, and the
/// ids they were given for; none when the command line names no file.
fn layered(command: Command, matches: &ArgMatches) -> Result<Option<(Command, Vec<String>)>> {
    let Some((name, sub_matches)) = matches.subcommand() else {
        return Ok(None);
    };
    if !LAYERED_COMMANDS.contains(&name) {
        return Ok(None);
    }
    let Some(path) = sub_matches.get_one::<PathBuf>("config") else {
        return Ok(None);
    };
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the configuration file {}", path.display()))?;
    let defaults =
        file_defaults(&text, name, &command).with_context(|| format!("{}", path.display()))?;
    let ids: Vec<String> = defaults.iter().map(|(id, _)| id.clone()).collect();
    let command = command.mut_subcommand(name, |mut sub| {
        for (id, values) in defaults {
            sub = sub.mut_arg(id, |arg| arg.default_values(values));
        }
        sub
    });
    Ok(Some((command, ids)))
}

/// The `[table]` of a configuration file as (argument id, values), each value checked by its
/// flag's parser; the file's other tables are checked too, so that a mistake in one is
/// found by whichever command reads the file first.
fn file_defaults(text: &str, table: &str, root: &Command) -> Result<Vec<(String, Vec<String>)>> {
    let file: toml::Table = text.parse().context("not a TOML file")?;
    let mut defaults = Vec::new();
    for (name, settings) in &file {
        let command = LAYERED_COMMANDS
            .contains(&name.as_str())
            .then(|| root.find_subcommand(name))
            .flatten();
        let (Some(command), Some(settings)) = (command, settings.as_table()) else {
            bail!(
                "`{name}` is not a table of settings: a configuration file has [{}]",
                LAYERED_COMMANDS.join("] and [")
            );
        };
        let checked = table_defaults(name, settings, command)?;
        if name == table {
            defaults = checked;
        }
    }
    Ok(defaults)
}

/// One table's settings as (argument id, values) of `command`.
fn table_defaults(
    table: &str,
    settings: &toml::Table,
    command: &Command,
) -> Result<Vec<(String, Vec<String>)>> {
    let mut defaults = Vec::new();
    for (key, value) in settings {
        let arg = setting(command, key).with_context(|| {
            format!(
                "[{table}] has no setting `{key}`; it has {}",
                setting_keys(command).join(", ")
            )
        })?;
        let values = toml_values(value, arg).with_context(|| format!("[{table}] {key}"))?;
        for value in &values {
            check_value(command, arg, value).with_context(|| format!("[{table}] {key}"))?;
        }
        defaults.push((arg.get_id().to_string(), values));
    }
    Ok(defaults)
}

/// `value` passes `arg`'s parser, as if given as its flag.
fn check_value(command: &Command, arg: &Arg, value: &str) -> Result<()> {
    let long = arg.get_long().context("a setting has a long flag")?;
    if matches!(arg.get_action(), ArgAction::SetTrue) {
        return match value {
            "true" | "false" => Ok(()),
            _ => bail!("'{value}' is not true or false"),
        };
    }
    command
        .clone()
        .no_binary_name(true)
        .try_get_matches_from([format!("--{long}={value}")])
        .map(drop)
        .map_err(|e| anyhow::anyhow!(clap_message(&e)))
}

/// The argument a file's key names: a long flag with `_` for `-`.
fn setting<'c>(command: &'c Command, key: &str) -> Option<&'c Arg> {
    command
        .get_arguments()
        .filter(|arg| is_setting(arg))
        .find(|arg| arg.get_long().is_some_and(|long| file_key(long) == key))
}

fn is_setting(arg: &Arg) -> bool {
    !arg.is_hide_set() && !NOT_SETTINGS.contains(&arg.get_id().as_str()) && arg.get_long().is_some()
}

fn file_key(long: &str) -> String {
    long.replace('-', "_")
}

fn setting_keys(command: &Command) -> Vec<String> {
    command
        .get_arguments()
        .filter(|arg| is_setting(arg))
        .filter_map(|arg| arg.get_long().map(file_key))
        .collect()
}

/// A TOML value as the text its flag would be given: an array only where the flag repeats.
fn toml_values(value: &toml::Value, arg: &Arg) -> Result<Vec<String>> {
    let repeats = matches!(arg.get_action(), ArgAction::Append);
    match value {
        toml::Value::Array(items) if repeats => items.iter().map(scalar).collect(),
        toml::Value::Array(_) => bail!("takes one value, not a list"),
        value => Ok(vec![scalar(value)?]),
    }
}

fn scalar(value: &toml::Value) -> Result<String> {
    Ok(match value {
        toml::Value::String(s) => s.clone(),
        toml::Value::Integer(i) => i.to_string(),
        toml::Value::Float(f) => f.to_string(),
        toml::Value::Boolean(b) => b.to_string(),
        toml::Value::Table(table) => inline_table(table),
        other => bail!("a {} is not a setting's value", other.type_str()),
    })
}

/// `table` in TOML's inline form: `{ url = "https://ci.example/hook", events = ["failed"] }`.
fn inline_table(table: &toml::Table) -> String {
    let entries: Vec<String> = table
        .iter()
        .map(|(key, value)| {
            let bare = !key.is_empty()
                && key
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
            if bare {
                format!("{key} = {value}")
            } else {
                format!("{} = {value}", toml::Value::String(key.clone()))
            }
        })
        .collect();
    format!("{{ {} }}", entries.join(", "))
}

/// The webhook endpoints of `serve --webhook` values, checked and with their secrets read:
/// each a URL, signed with the secret in `secret_file`, or a `[[serve.webhook]]` table in its
/// inline form, which may name a secret of its own. The errors name the endpoint without
/// repeating the table's text, and never hold a secret.
pub fn webhook_endpoints(
    values: &[String],
    secret_file: Option<&Path>,
) -> Result<Vec<WebhookEndpoint>> {
    #[derive(serde::Deserialize)]
    struct Entry {
        webhook: WebhookSpec,
    }
    let mut endpoints = Vec::new();
    for (n, value) in values.iter().enumerate() {
        let mut spec = if value.trim_start().starts_with('{') {
            toml::from_str::<Entry>(&format!("webhook = {value}"))
                .map_err(|e| {
                    anyhow::anyhow!("webhook table {} of the settings: {}", n + 1, e.message())
                })?
                .webhook
        } else {
            WebhookSpec::new(value, None)
        };
        if spec.secret_file.is_none() && spec.secret_env.is_none() {
            spec.secret_file = secret_file.map(Path::to_path_buf);
        }
        endpoints.push(WebhookEndpoint::load(&spec)?);
    }
    Ok(endpoints)
}

/// clap's message for a value, without its `error: ` prefix and usage lines.
fn clap_message(error: &clap::Error) -> String {
    let text = error.to_string();
    let first = text.lines().next().unwrap_or_default();
    first.strip_prefix("error: ").unwrap_or(first).to_string()
}

/// With `--print-config`: prints the layered command's settings as TOML, in `command`'s
/// order, and exits.
fn print_config_and_exit(command: &Command, matches: &ArgMatches, from_file: &[String]) {
    let Some((name, sub_matches)) = matches.subcommand() else {
        return;
    };
    if !LAYERED_COMMANDS.contains(&name) || !sub_matches.get_flag("print_config") {
        return;
    }
    let Some(sub) = command.find_subcommand(name) else {
        return;
    };
    print!("{}", settings_toml(name, sub, sub_matches, from_file));
    std::process::exit(0);
}

/// `[name]` and one line per setting: `key = value  # layer`; secrets are not shown.
fn settings_toml(
    name: &str,
    command: &Command,
    matches: &ArgMatches,
    from_file: &[String],
) -> String {
    let mut out = format!("[{name}]\n");
    for arg in command.get_arguments().filter(|arg| is_setting(arg)) {
        let id = arg.get_id().as_str();
        let Some(long) = arg.get_long() else { continue };
        let key = file_key(long);
        let layer = match matches.value_source(id) {
            Some(ValueSource::CommandLine) => "flag",
            Some(ValueSource::EnvVariable) => "env",
            Some(ValueSource::DefaultValue) if from_file.iter().any(|f| f == id) => "file",
            Some(_) => "default",
            None => {
                out.push_str(&format!("# {key}: not set\n"));
                continue;
            }
        };
        if arg.is_hide_env_values_set() {
            out.push_str(&format!("# {key} = (secret)  # {layer}\n"));
            continue;
        }
        let values: Vec<String> = matches
            .get_raw(id)
            .into_iter()
            .flatten()
            .map(|v| toml_value(&v.to_string_lossy()))
            .collect();
        let value = if matches!(arg.get_action(), ArgAction::Append) {
            format!("[{}]", values.join(", "))
        } else {
            values.into_iter().next().unwrap_or_default()
        };
        out.push_str(&format!("{key} = {value}  # {layer}\n"));
    }
    out
}

/// A value as TOML of its own type where it reads back to the same text ([`scalar`]): a number or
/// a boolean bare, anything else a string.
fn toml_value(raw: &str) -> String {
    let typed = if let Ok(i) = raw.parse::<i64>() {
        Some(toml::Value::Integer(i))
    } else if let Ok(b) = raw.parse::<bool>() {
        Some(toml::Value::Boolean(b))
    } else {
        raw.parse::<f64>()
            .ok()
            .filter(|f| f.is_finite())
            .map(toml::Value::Float)
    };
    typed
        .filter(|value| scalar(value).is_ok_and(|text| text == raw))
        .unwrap_or_else(|| toml::Value::String(raw.to_owned()))
        .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Cli;
    use clap::CommandFactory;

    /// The layered command, its matches and the ids the file gave.
    fn matches_with_file(args: &[&str], file: &str) -> Result<(Command, ArgMatches, Vec<String>)> {
        let dir = tempfile::tempdir()?;
        let path = dir.path().join("pointfarm.toml");
        std::fs::write(&path, file)?;
        let mut argv: Vec<OsString> = vec!["pointfarm".into()];
        argv.extend(args.iter().map(OsString::from));
        argv.extend(["--config".into(), path.clone().into_os_string()]);
        let first = Cli::command().try_get_matches_from(argv.clone())?;
        let (command, ids) = layered(Cli::command(), &first)?.context("a layered command")?;
        let matches = command.clone().try_get_matches_from(argv)?;
        Ok((command, matches, ids))
    }

    fn sub(matches: &ArgMatches) -> &ArgMatches {
        matches.subcommand().expect("a subcommand").1
    }

    #[test]
    fn the_file_fills_in_what_the_flags_do_not_give() {
        let file = "[serve]\nlease_timeout = 5\nmax_frame_attempts = 7\ndata_root = [\"/a\", \"/b\"]\ninsecure = true\n\n[worker]\ncache_gib = 3\n";
        let (command, matches, ids) =
            matches_with_file(&["serve", "--max-frame-attempts", "2"], file).expect("layered");
        let serve = sub(&matches);
        assert_eq!(serve.get_one::<f64>("lease_timeout"), Some(&5.0));
        assert_eq!(serve.get_one::<u32>("max_frame_attempts"), Some(&2));
        assert_eq!(
            serve.value_source("max_frame_attempts"),
            Some(ValueSource::CommandLine)
        );
        let roots: Vec<&PathBuf> = serve.get_many("data_roots").expect("roots").collect();
        assert_eq!(roots, [&PathBuf::from("/a"), &PathBuf::from("/b")]);
        assert!(serve.get_flag("insecure"));
        let serve_command = command.find_subcommand("serve").expect("serve");
        let printed = settings_toml("serve", serve_command, serve, &ids);
        assert!(printed.contains("lease_timeout = 5  # file"), "{printed}");
        assert!(
            printed.contains("max_frame_attempts = 2  # flag"),
            "{printed}"
        );
        assert!(
            printed.contains("data_root = [\"/a\", \"/b\"]  # file"),
            "{printed}"
        );
        assert!(
            printed.contains("listen = \"127.0.0.1:50051\"  # default"),
            "{printed}"
        );
    }

    #[test]
    fn the_printed_settings_read_back_as_a_file_to_the_same_settings() {
        let file =
            "[serve]\nlease_timeout = 2.5\nmax_frames = 500\ninsecure = true\nworker_tag = \"7\"\n";
        let printed = |file: &str| {
            let (command, matches, ids) = matches_with_file(&["serve"], file).expect("layered");
            let serve_command = command.find_subcommand("serve").expect("serve");
            settings_toml("serve", serve_command, sub(&matches), &ids)
        };
        let first = printed(file);
        for line in ["lease_timeout = 2.5", "max_frames = 500", "insecure = true"] {
            assert!(first.contains(&format!("{line}  # file")), "{first}");
        }
        // A value of a string setting that looks like a number reads back the same either way.
        assert!(first.contains("worker_tag = [7]  # file"), "{first}");
        // The same settings, each from the file (the order of a command's settings follows
        // where the file's values were set).
        let settings = |printed: String| {
            let mut lines: Vec<String> = printed
                .replace("# default", "# file")
                .lines()
                .map(str::to_owned)
                .collect();
            lines.sort();
            lines
        };
        assert_eq!(settings(printed(&first)), settings(first));
    }

    #[test]
    fn a_bad_file_names_the_table_and_the_key() {
        let message = |file: &str| {
            format!(
                "{:#}",
                matches_with_file(&["serve"], file).expect_err("refused")
            )
        };
        let range = message("[serve]\nmax_frame_attempts = 0\n");
        assert!(range.contains("[serve] max_frame_attempts"), "{range}");
        assert!(range.contains("'0'"), "{range}");
        let unknown = message("[serve]\nlisten_on = \"x\"\n");
        assert!(unknown.contains("no setting `listen_on`"), "{unknown}");
        assert!(unknown.contains("data_dir"), "{unknown}");
        let table = message("[daemon]\nlisten = \"x\"\n");
        assert!(table.contains("`daemon` is not a table"), "{table}");
        let list = message("[serve]\nlisten = [\"a\", \"b\"]\n");
        assert!(list.contains("[serve] listen: takes one value"), "{list}");
        let syntax = message("[serve\n");
        assert!(syntax.contains("not a TOML file"), "{syntax}");
        let hidden = message("[worker]\nsupervised = true\n");
        assert!(hidden.contains("no setting `supervised`"), "{hidden}");
    }

    /// `[[serve.webhook]]` tables reach `--webhook` in their inline form and are read back
    /// whole; a bare URL is signed with `--webhook-secret-file`; a bad table is refused
    /// naming its key.
    #[test]
    fn webhook_tables_become_endpoints() {
        use pointfarm_daemon::webhooks::JobEnd;
        let dir = tempfile::tempdir().expect("tempdir");
        let secret = dir.path().join("secret");
        std::fs::write(&secret, "s3cret\n").expect("secret");
        let file = format!(
            "[[serve.webhook]]\nurl = \"https://ci.example/hook\"\nsecret_file = {}\n\
             events = [\"failed\"]\n\n[[serve.webhook]]\nurl = \"http://127.0.0.1:8080/\"\n",
            toml::Value::String(secret.display().to_string())
        );
        let (_, matches, _) = matches_with_file(&["serve"], &file).expect("layered");
        let values: Vec<String> = sub(&matches)
            .get_many::<String>("webhooks")
            .expect("webhooks")
            .cloned()
            .collect();
        assert_eq!(values.len(), 2, "{values:?}");
        let unsigned = format!(
            "{:#}",
            webhook_endpoints(&values, None).expect_err("refused")
        );
        assert!(
            unsigned.contains("webhook http://127.0.0.1:8080/: no secret"),
            "{unsigned}"
        );
        let endpoints = webhook_endpoints(&values, Some(&secret)).expect("accepted");
        assert_eq!(endpoints[0].shown_url(), "https://ci.example/hook");
        assert!(endpoints[0].wants(JobEnd::Failed) && !endpoints[0].wants(JobEnd::Cancelled));
        assert!(JobEnd::ALL.iter().all(|end| endpoints[1].wants(*end)));

        let misspelt = ["{ url = \"https://ci.example/hook\", secrt_file = \"x\" }".to_owned()];
        let refused = format!(
            "{:#}",
            webhook_endpoints(&misspelt, None).expect_err("refused")
        );
        assert!(refused.contains("unknown field `secrt_file`"), "{refused}");
    }

    /// Every setting can come from each layer: a flag, a `POINTFARM_*` variable, a file key.
    #[test]
    fn every_setting_of_serve_and_worker_has_an_environment_variable() {
        let root = Cli::command();
        for name in LAYERED_COMMANDS {
            let command = root.find_subcommand(name).expect("a layered command");
            let mut seen = Vec::new();
            for arg in command.get_arguments().filter(|arg| is_setting(arg)) {
                let env = arg.get_env().map(|env| env.to_string_lossy().into_owned());
                let env =
                    env.unwrap_or_else(|| panic!("{name} --{:?} has no variable", arg.get_long()));
                assert!(env.starts_with("POINTFARM_"), "{name}: {env}");
                assert!(!seen.contains(&env), "{name}: {env} twice");
                seen.push(env);
            }
            assert!(seen.len() > 10, "{name}: {seen:?}");
        }
    }
}
