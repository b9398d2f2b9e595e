//! Why a command failed, and the one line that says so on stderr.

use mbfg::Error;

/// Why a command failed: bad input (exit 2), a run that failed or ended early
/// (exit 1), or a run the user interrupted (exit 130).
pub enum Failure {
    Input(String),
    Run(String),
    Interrupted(String),
}

impl From<String> for Failure {
    fn from(m: String) -> Self {
        Failure::Input(m)
    }
}

/// The longest error message: with `error: `, a line of 300 characters at most;
/// longer messages are cut with an ellipsis.
const MAX_MESSAGE_CHARS: usize = 300 - "error: ".len();

/// What a cut message keeps of its end: a failure's last words are what to do about
/// it (`… (the fixed-lag smoother (--window N) or a smaller dt may converge)`).
const KEPT_END_CHARS: usize = 110;

/// One line of at most [`MAX_MESSAGE_CHARS`] characters: a longer one loses the
/// middle, marked by an ellipsis, and keeps its beginning (what failed, where) and
/// its end (the hint).
pub fn shorten(message: &str) -> String {
    let line = message.replace(['\n', '\r'], " ");
    let chars: Vec<char> = line.chars().collect();
    if chars.len() <= MAX_MESSAGE_CHARS {
        return line;
    }
    // Cut between words where one is near (a name or number is not cut in two).
    let near = 30;
    let mut head = MAX_MESSAGE_CHARS - 1 - KEPT_END_CHARS;
    if let Some(space) = (head.saturating_sub(near)..head)
        .rev()
        .find(|&i| chars[i] == ' ')
    {
        head = space + 1;
    }
    let mut tail = chars.len() - KEPT_END_CHARS;
    if let Some(space) = (tail..(tail + near).min(chars.len())).find(|&i| chars[i] == ' ') {
        tail = space;
    }
    let mut cut: String = chars[..head].iter().collect();
    cut.push('…');
    cut.extend(&chars[tail..]);
    cut
}

/// clap's error as one line: its first line without the `error: ` prefix, and where
/// to read more.
pub fn clap_line(e: &clap::Error) -> String {
    let text = e.render().to_string();
    // The first paragraph (a list of missing arguments runs over several lines).
    let first: Vec<&str> = text
        .lines()
        .map(str::trim)
        .skip_while(|l| l.is_empty())
        .take_while(|l| !l.is_empty())
        .collect();
    let first = first.join(" ");
    let first = first.strip_prefix("error: ").unwrap_or(&first);
    shorten(&format!("{first} (mbfg --help lists the arguments)"))
}

/// The message of a library error without the variant's prefix for bad arguments.
pub fn plain(e: Error) -> String {
    match e {
        Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_message_keeps_its_beginning_and_its_hint() {
        let message = format!(
            "step 12 (t = 0.012 s) did not converge: {}; nothing was written (the fixed-lag \
             smoother (--window N) or a smaller dt may converge)",
            "x".repeat(400)
        );
        let line = shorten(&message);
        assert!(line.chars().count() <= MAX_MESSAGE_CHARS);
        assert!(line.starts_with("step 12 (t = 0.012 s) did not converge: "));
        assert!(line.ends_with("or a smaller dt may converge)"), "{line}");
        assert!(line.contains('…'));
        assert_eq!(shorten("short"), "short");
    }

    #[test]
    fn a_long_message_is_cut_between_words() {
        let items: Vec<String> = (0..40)
            .map(|k| format!("coupler{k}: distance(P{k},Q{k}) (|Φ| = 2.277e-1)"))
            .collect();
        let line = shorten(&format!("constraints left violated: {}", items.join(", ")));
        assert!(line.chars().count() <= MAX_MESSAGE_CHARS);
        let (head, tail) = line.split_once('…').unwrap();
        assert!(head.ends_with(' '), "{line}");
        assert!(tail.starts_with(' '), "{line}");
        assert!(line.ends_with("(|Φ| = 2.277e-1)"), "{line}");
    }
}
