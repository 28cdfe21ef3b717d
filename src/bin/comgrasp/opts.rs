//! A small `--name value` / `--name=value` / `--flag` parser for the subcommands that do not
//! have their own (the library crate keeps its dependency set, so no clap).
use std::collections::HashMap;
use std::str::FromStr;

pub struct Opts {
    values: HashMap<String, String>,
    flags: Vec<String>,
    command: &'static str,
}

impl Opts {
    /// `values`: options that take a value; `flags`: options that take none.
    pub fn parse(command: &'static str, args: &[String], values: &[&str], flags: &[&str]) -> Result<Opts, String> {
        let mut o = Opts { values: HashMap::new(), flags: Vec::new(), command };
        let mut it = args.iter();
        while let Some(arg) = it.next() {
            let (name, inline) = match arg.split_once('=') {
                Some((n, v)) if n.starts_with("--") => (n, Some(v.to_string())),
                _ => (arg.as_str(), None),
            };
            if flags.contains(&name) {
                if inline.is_some() {
                    return Err(format!("{command}: {name} takes no value"));
                }
                o.flags.push(name.to_string());
            } else if values.contains(&name) {
                let v = match inline {
                    Some(v) => v,
                    None => it.next().cloned().ok_or_else(|| format!("{command}: {name} needs a value"))?,
                };
                o.values.insert(name.to_string(), v);
            } else {
                return Err(format!("{command}: unknown argument {arg:?}"));
            }
        }
        Ok(o)
    }

    pub fn flag(&self, name: &str) -> bool {
        self.flags.iter().any(|f| f == name)
    }

    pub fn str(&self, name: &str) -> Option<&str> {
        self.values.get(name).map(String::as_str)
    }

    pub fn required(&self, name: &str) -> Result<&str, String> {
        self.str(name).ok_or_else(|| format!("{}: {name} is required", self.command))
    }

    pub fn num<T: FromStr>(&self, name: &str, default: T) -> Result<T, String> {
        match self.str(name) {
            None => Ok(default),
            Some(v) => v.parse().map_err(|_| format!("{}: {name} {v:?} is not a valid number", self.command)),
        }
    }
}
