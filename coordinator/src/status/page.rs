//! The status page's HTML: one self-refreshing page drawn by the server from a
//! [`StatusSnapshot`], the loss curve as inline SVG, no script. Every string that came from
//! outside (worker names, reasons, locations) is escaped.

use std::fmt::Write;

use telemetry::plot::{Chart, Figure, Panel, Series};

use crate::job::snapshot::StatusSnapshot;

/// Seconds between the page's reloads.
pub const REFRESH_SECONDS: u32 = 5;

const STYLE: &str = "body{font-family:sans-serif;margin:2em;color:#222}\
table{border-collapse:collapse;margin-bottom:1.5em}td,th{border:1px solid #ccc;padding:4px 8px;text-align:left}\
th{background:#f3f3f3}.bad{color:#b00020;font-weight:bold}.bar{width:40em;background:#eee;height:1em}\
.fill{background:#3a7;height:1em}code{font-size:90%}";

/// `text` with HTML's special characters escaped.
pub fn escape(text: &str) -> String {
    text.chars()
        .map(|c| match c {
            '&' => "&amp;".into(),
            '<' => "&lt;".into(),
            '>' => "&gt;".into(),
            '"' => "&quot;".into(),
            '\'' => "&#39;".into(),
            c => c.to_string(),
        })
        .collect()
}

/// A page with `title` around `body`, reloading itself when `refresh`.
fn document(title: &str, body: &str, refresh: bool) -> String {
    let reload = if refresh {
        format!("<meta http-equiv=\"refresh\" content=\"{REFRESH_SECONDS}\">")
    } else {
        String::new()
    };
    format!(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\">{reload}<title>{}</title>\
         <style>{STYLE}</style></head><body>{body}</body></html>",
        escape(title)
    )
}

/// The form that asks for the job token, with `problem` above it when the last try failed.
pub fn login(problem: Option<&str>) -> String {
    let problem = problem.map_or(String::new(), |p| {
        format!("<p class=\"bad\">{}</p>", escape(p))
    });
    document(
        "xfactor: sign in",
        &format!(
            "<h1>xfactor job status</h1>{problem}<p>This page shows the job to holders of its \
             token (the cluster YAML's <code>auth</code>).</p><form method=\"post\" action=\"/login\">\
             <label>Job token <input type=\"password\" name=\"token\" autofocus></label> \
             <button type=\"submit\">Show the job</button></form>"
        ),
        false,
    )
}

/// `seconds` as `1h02m`, `3m05s` or `12s`.
fn duration(seconds: f64) -> String {
    let whole = seconds.max(0.0).round() as u64;
    match (whole / 3600, (whole / 60) % 60, whole % 60) {
        (0, 0, s) => format!("{s}s"),
        (0, m, s) => format!("{m}m{s:02}s"),
        (h, m, _) => format!("{h}h{m:02}m"),
    }
}

/// The job's page.
pub fn render(snapshot: &StatusSnapshot) -> String {
    let mut body = String::new();
    header(&mut body, snapshot);
    workers(&mut body, snapshot);
    body.push_str("<h2>Loss</h2>");
    body.push_str(&loss_svg(snapshot));
    timeline(&mut body, snapshot);
    commits(&mut body, snapshot);
    document(&format!("xfactor: {}", snapshot.job), &body, true)
}

fn header(body: &mut String, s: &StatusSnapshot) {
    let done = if s.job_steps_total == 0 {
        0.0
    } else {
        100.0 * s.job_steps_done as f64 / s.job_steps_total as f64
    };
    let eta = s.eta_s.map_or("-".into(), duration);
    let _ = write!(
        body,
        "<h1>{}</h1><p>phase <b>{}</b> &middot; <b>{}</b> &middot; generation {} &middot; \
         step {}/{} &middot; job {}/{} steps ({done:.1}%) &middot; ETA {eta} &middot; \
         loss {:.4} &middot; {:.1} samples/s</p><div class=\"bar\"><div class=\"fill\" \
         style=\"width:{done:.1}%\"></div></div>",
        escape(&s.job),
        escape(&s.phase),
        escape(&s.state),
        s.generation,
        s.step,
        s.stage_steps,
        s.job_steps_done,
        s.job_steps_total,
        s.last_loss,
        s.samples_per_s,
    );
    if let Some(failing) = s.store_failing_s {
        let _ = write!(
            body,
            "<p class=\"bad\">The object store has been failing for {}.</p>",
            duration(failing)
        );
    }
    if let Some(evaluation) = &s.evaluation {
        let _ = write!(
            body,
            "<p>Evaluation report: <code>{}/report.md</code></p>",
            escape(evaluation)
        );
    }
}

fn workers(body: &mut String, s: &StatusSnapshot) {
    body.push_str(
        "<h2>Workers</h2><table><tr><th>id</th><th>name</th><th>device</th><th>state</th>\
         <th>samples/s</th><th>last heartbeat</th><th>faults blamed</th></tr>",
    );
    for w in &s.workers {
        let class = if w.state == "lost" {
            " class=\"bad\""
        } else {
            ""
        };
        let _ = write!(
            body,
            "<tr{class}><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{:.1}</td>\
             <td>{} ago</td><td>{}</td></tr>",
            w.id,
            escape(&w.name),
            escape(&w.device),
            escape(&w.state),
            w.samples_per_s,
            duration(w.heartbeat_age_s),
            w.faults,
        );
    }
    body.push_str("</table>");
}

fn timeline(body: &mut String, s: &StatusSnapshot) {
    body.push_str("<h2>Generations</h2><table><tr><th>generation</th><th>event</th></tr>");
    for entry in &s.timeline {
        let class = if entry.event.starts_with("ended") {
            " class=\"bad\""
        } else {
            ""
        };
        let _ = write!(
            body,
            "<tr{class}><td>{}</td><td>{}</td></tr>",
            entry.generation,
            escape(&entry.event)
        );
    }
    body.push_str("</table><h2>Faults</h2>");
    if s.faults.is_empty() {
        body.push_str("<p>none</p>");
    } else {
        body.push_str("<ul>");
        for fault in &s.faults {
            let _ = write!(body, "<li class=\"bad\">{}</li>", escape(fault));
        }
        body.push_str("</ul>");
    }
}

fn commits(body: &mut String, s: &StatusSnapshot) {
    body.push_str("<h2>Commits</h2><table><tr><th>phase</th><th>step</th><th>where</th></tr>");
    for c in &s.commits {
        let _ = write!(
            body,
            "<tr><td>{}</td><td>{}</td><td><code>{}</code></td></tr>",
            escape(&c.phase),
            c.step,
            escape(&c.location)
        );
    }
    body.push_str("</table>");
}

/// The loss curve as inline SVG (a line saying why when there is none yet).
fn loss_svg(s: &StatusSnapshot) -> String {
    if s.loss.len() < 2 {
        return "<p>No steps yet.</p>".into();
    }
    let figure = Figure {
        title: String::new(),
        panels: vec![Panel {
            title: "loss of the global batch (both stages)".into(),
            x_label: "job step".into(),
            y_label: "loss".into(),
            log_y: false,
            equal_aspect: false,
            series: vec![Series {
                name: "loss".into(),
                points: s
                    .loss
                    .iter()
                    .map(|&(x, y)| (x as f64, f64::from(y)))
                    .collect(),
            }],
        }],
        panel_size: (800, 300),
    };
    figure.to_svg().unwrap_or_else(|e| {
        format!(
            "<p>The curve could not be drawn: {}</p>",
            escape(&e.to_string())
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::job::snapshot::{TimelineEntry, WorkerView};

    fn snapshot() -> StatusSnapshot {
        StatusSnapshot {
            job: "demo".into(),
            phase: "stage1".into(),
            state: "running".into(),
            generation: 2,
            step: 40,
            stage_steps: 100,
            job_steps_done: 40,
            job_steps_total: 150,
            eta_s: Some(75.0),
            last_loss: 0.25,
            samples_per_s: 30.0,
            store_failing_s: None,
            workers: vec![WorkerView {
                id: 7,
                name: "<script>alert(1)</script>".into(),
                device: "cpu".into(),
                samples_per_s: 15.0,
                heartbeat_age_s: 0.2,
                state: "lost".into(),
                faults: 1,
            }],
            timeline: vec![TimelineEntry {
                generation: 1,
                event: "ended at step 12: rank 1 (w1) failed: killed".into(),
            }],
            faults: vec!["w1 blamed".into()],
            commits: vec![],
            loss: vec![(0, 0.5), (10, 0.4), (20, 0.3)],
            evaluation: None,
        }
    }

    #[test]
    fn the_page_shows_the_job_its_workers_and_faults_and_escapes_what_came_from_outside() {
        let page = render(&snapshot());
        for shown in [
            "demo",
            "step 40/100",
            "ETA 1m15s",
            "&lt;script&gt;",
            "ended at step 12",
            "w1 blamed",
            "<svg",
            "http-equiv=\"refresh\"",
        ] {
            assert!(page.contains(shown), "{shown} missing");
        }
        assert!(!page.contains("<script>"));
    }

    #[test]
    fn durations_read_as_an_operator_would_say_them() {
        assert_eq!(duration(12.4), "12s");
        assert_eq!(duration(185.0), "3m05s");
        assert_eq!(duration(3720.0), "1h02m");
    }
}
