//! "Did you mean …?" for a name the scene does not know: the closest known names by
//! edit distance, when they are close enough to be a slip of the keyboard.

/// Optimal string alignment distance (Levenshtein with adjacent transpositions), on
/// characters, not bytes.
fn distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    let mut d = vec![vec![0usize; b.len() + 1]; a.len() + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for j in 0..=b.len() {
        d[0][j] = j;
    }
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut v = (d[i - 1][j] + 1)
                .min(d[i][j - 1] + 1)
                .min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                v = v.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = v;
        }
    }
    d[a.len()][b.len()]
}

/// The known names closest to `name` (at most three, nearest first), among those within
/// a third of its length, case aside (so a name of one or two characters matches only
/// in another case: any other short name is one edit away).
pub fn closest<'a>(name: &str, known: impl IntoIterator<Item = &'a str>) -> Vec<&'a str> {
    // Names far longer than any scene's are not compared (the cost is their product).
    if name.chars().count() > 64 {
        return Vec::new();
    }
    let lower = name.to_lowercase();
    let limit = name.chars().count() / 3;
    let mut scored: Vec<(usize, &str)> = known
        .into_iter()
        .filter(|k| k.chars().count() <= 64)
        .map(|k| (distance(&lower, &k.to_lowercase()), k))
        .filter(|(d, _)| *d <= limit)
        .collect();
    scored.sort_by_key(|(d, _)| *d);
    scored.dedup_by_key(|(_, k)| *k);
    scored.into_iter().take(3).map(|(_, k)| k).collect()
}

/// `; did you mean 'psi'?` (or `'a' or 'b'`), empty when nothing is close.
pub fn did_you_mean<'a>(name: &str, known: impl IntoIterator<Item = &'a str>) -> String {
    let near = closest(name, known);
    if near.is_empty() {
        return String::new();
    }
    let quoted: Vec<String> = near.iter().map(|k| format!("'{k}'")).collect();
    format!("; did you mean {}?", quoted.join(" or "))
}

/// `; the scene's <what> are a, b, c` (the first `MAX_LISTED` of them), for a name
/// that nothing is close to.
pub fn listed<'a>(what: &str, known: impl IntoIterator<Item = &'a str>) -> String {
    const MAX_LISTED: usize = 12;
    let all: Vec<&str> = known.into_iter().collect();
    if all.is_empty() {
        return format!("; the scene has no {what}");
    }
    let more = match all.len() > MAX_LISTED {
        true => format!(" and {} more", all.len() - MAX_LISTED),
        false => String::new(),
    };
    let shown: Vec<&str> = all.iter().take(MAX_LISTED).copied().collect();
    format!("; the scene's {what} are {}{more}", shown.join(", "))
}

/// [`did_you_mean`], or else [`listed`].
pub fn hint<'a>(
    name: &str,
    what: &str,
    known: impl IntoIterator<Item = &'a str> + Clone,
) -> String {
    let near = did_you_mean(name, known.clone());
    match near.is_empty() {
        true => listed(what, known),
        false => near,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_slip_of_the_keyboard_is_found() {
        assert_eq!(distance("thetta", "theta"), 1);
        assert_eq!(distance("pis", "psi"), 1);
        assert_eq!(distance("psy", "psi"), 1);
        assert_eq!(distance("omega", "theta"), 3);
        assert_eq!(distance("ab", "ba"), 1);
        let known = ["theta", "psi", "T.x", "T.y"];
        assert_eq!(closest("thetta", known), vec!["theta"]);
        assert_eq!(closest("Theta", known), vec!["theta"]);
        assert_eq!(closest("psy", known), vec!["psi"]);
        assert_eq!(closest("T.z", known), vec!["T.x", "T.y"]);
        assert!(closest("omega", known).is_empty());
        assert!(closest("k", ["c", "L"]).is_empty());
        assert_eq!(closest("l", ["c", "L"]), vec!["L"]);
        assert_eq!(did_you_mean("psy", known), "; did you mean 'psi'?");
        assert_eq!(
            hint("omega", "angles", ["theta", "psi"]),
            "; the scene's angles are theta, psi"
        );
    }
}
