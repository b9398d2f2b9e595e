//! `mbfg <command> --help` lists every value its options accept, and describes them
//! as the run behaves; a run whose t_end is off the step grid says where it ended.

mod common;

use common::{mbfg, stderr};
use mbfg::derived::Group;
use mbfg::forward::Integrator;

const COMMANDS: [&str; 5] = ["check", "simulate", "inverse", "measure", "estimate"];

fn help(command: &str) -> String {
    let out = mbfg(&[command, "--help"]);
    assert!(out.status.success(), "{}", stderr(&out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The paragraph of one option in a long help text.
fn option_help<'a>(help: &'a str, option: &str) -> Option<&'a str> {
    let start = help.find(&format!("      {option} "))?;
    let rest = &help[start..];
    let end = rest[1..].find("\n      -").map_or(rest.len(), |e| e + 1);
    Some(&rest[..end])
}

/// The values clap names when an option is given one it does not accept.
fn accepted(command: &str, option: &str) -> Vec<String> {
    let out = mbfg(&[command, option, "no-such-value", "--help"]);
    let err = stderr(&out);
    let list = err
        .split("[possible values: ")
        .nth(1)
        .and_then(|r| r.split(']').next())
        .unwrap_or_else(|| panic!("{command} {option}: no list of values in\n{err}"));
    list.split(", ").map(str::to_string).collect()
}

#[test]
fn every_value_an_option_accepts_is_in_its_help() {
    let mut checked = 0;
    for command in COMMANDS {
        let help = help(command);
        // Options whose values clap enumerates: the parser's list against the help's.
        for line in help.lines().filter(|l| l.trim_start().starts_with("--")) {
            let option = line.trim().split([' ', '=']).next().unwrap();
            let Some(paragraph) = option_help(&help, option) else {
                continue;
            };
            if !paragraph.contains("ossible values") {
                continue;
            }
            for value in accepted(command, option) {
                assert!(
                    paragraph.contains(&format!(" {value}"))
                        || paragraph.contains(&format!("- {value}:")),
                    "mbfg {command} --help: {option} accepts `{value}`, not listed:\n{paragraph}"
                );
                checked += 1;
            }
        }
        // --columns takes a hand-written list: every group must be in it.
        if let Some(paragraph) = option_help(&help, "--columns") {
            for g in Group::ALL {
                assert!(
                    paragraph.contains(&format!("`{}`", g.name())),
                    "mbfg {command} --help: --columns does not list `{}`:\n{paragraph}",
                    g.name()
                );
                checked += 1;
            }
        }
    }
    for i in Integrator::ALL {
        let simulate = help("simulate");
        let paragraph = option_help(&simulate, "--integrator").unwrap();
        assert!(paragraph.contains(i.name()), "{paragraph}");
    }
    assert!(checked >= 20, "only {checked} values checked");
}

#[test]
fn dc_integrators_auto_is_described_as_it_runs() {
    let simulate = help("simulate");
    let paragraph = option_help(&simulate, "--dc-integrators").unwrap();
    let auto = &paragraph[paragraph.find("(`full`").expect(paragraph)..];
    let auto = &auto[auto.find(" or ").expect(paragraph)..];
    // `auto` runs tangent integrators first (square steps) and falls back to the paper's.
    assert!(
        auto.find("`tangent`") < auto.find("`full`") && auto.contains("(`auto`)"),
        "{paragraph}"
    );
    let out = mbfg(&[
        "simulate",
        "scenes/fourbar.yaml",
        "--dt",
        "0.01",
        "--t-end",
        "0.1",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stderr(&out).contains("square steps"), "{}", stderr(&out));
}

#[test]
fn an_end_time_off_the_step_grid_is_stated_in_the_summary() {
    let run = |t_end: &str, dt: &str| {
        let out = mbfg(&[
            "simulate",
            "scenes/pendulum.yaml",
            "--dt",
            dt,
            "--t-end",
            t_end,
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
        let csv = String::from_utf8_lossy(&out.stdout).into_owned();
        (stderr(&out), common::last_t(&csv))
    };
    let (summary, last) = run("0.2005", "0.001");
    assert_eq!(last, 0.201);
    assert!(
        summary.contains("ends at t = 0.201 s, the whole step nearest t_end = 0.2005 s"),
        "{summary}"
    );
    let (summary, last) = run("0.1", "0.003");
    assert_eq!(last, 0.099);
    assert!(summary.contains("ends at t = 0.099 s"), "{summary}");
    let (summary, _) = run("0.3", "0.1");
    assert!(!summary.contains("ends at"), "{summary}");
}
