//! Which training views a run trains on (`--train-views N|LIST`): all of them, a count
//! spread over the split, or named indices. Few-view figures depend on exactly which
//! photos were kept, so the choice is written to the run's config and to `metrics.json`.

use serde::{Deserialize, Serialize};

use crate::error::{NerfError, Result};

/// A subset of the training split, by index into it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum TrainViews {
    /// `n` views at `k * total / n` (the `views-25` and `views-50` presets: the paper's
    /// ablations; a count in configs written before the other choices existed).
    Evenly(usize),
    /// These indices into the split (kept in ascending order).
    List(Vec<usize>),
    /// `n` views at `round(linspace(0, total - 1, n))`: RegNeRF's and FreeNeRF's choice
    /// (the first and the last view, the rest evenly between).
    Spread { spread: usize },
}

impl TrainViews {
    /// The indices kept of a split of `total` views, ascending; an error naming the index
    /// when a list names one past the split, twice, or none, or naming the count when it
    /// asks for more views than the split holds.
    pub fn indices(&self, total: usize) -> Result<Vec<usize>> {
        match self {
            TrainViews::Evenly(n) => Ok(evenly_kept(total, *n)),
            TrainViews::Spread { spread } if *spread > total => Err(NerfError::Config(format!(
                "--train-views {spread}: the training split holds only {total} views"
            ))),
            TrainViews::Spread { spread } => Ok(spread_kept(total, *spread)),
            TrainViews::List(list) => {
                let bad = |what: String| NerfError::Config(format!("--train-views: {what}"));
                if list.is_empty() {
                    return Err(bad("the list names no view".into()));
                }
                for (k, &i) in list.iter().enumerate() {
                    if i >= total {
                        return Err(bad(format!(
                            "view {i} is past the training split's {total} views (indices start at 0)"
                        )));
                    }
                    if list[..k].contains(&i) {
                        return Err(bad(format!("view {i} is named twice")));
                    }
                }
                let mut kept = list.clone();
                kept.sort_unstable();
                Ok(kept)
            }
        }
    }

    /// Whether this keeps fewer views than a split of `total` holds.
    pub fn is_subset(&self, total: usize) -> bool {
        self.indices(total).is_ok_and(|kept| kept.len() < total)
    }
}

/// As `--train-views` takes it (a count, or indices joined by commas); the presets'
/// even choice as `25 (evenly)`.
impl std::fmt::Display for TrainViews {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TrainViews::Evenly(n) => write!(f, "{n} (evenly)"),
            TrainViews::Spread { spread } => write!(f, "{spread}"),
            TrainViews::List(list) if list.len() == 1 => write!(f, "{},", list[0]),
            TrainViews::List(list) => {
                let parts: Vec<String> = list.iter().map(|i| i.to_string()).collect();
                write!(f, "{}", parts.join(","))
            }
        }
    }
}

/// `--train-views N|LIST`: a count (`3`: RegNeRF's spread) or indices (`1,10,19`).
pub fn parse_train_views(s: &str) -> std::result::Result<TrainViews, String> {
    let s = s.trim();
    if !s.contains(',') {
        return match s.parse::<usize>() {
            Ok(0) => Err("a count of views must be at least 1".into()),
            Ok(n) => Ok(TrainViews::Spread { spread: n }),
            Err(_) => Err(format!(
                "expected a count (3) or a list of view indices (1,10,19), got {s:?}"
            )),
        };
    }
    let list: std::result::Result<Vec<usize>, _> = s
        .split(',')
        .filter(|p| !p.trim().is_empty())
        .map(|p| p.trim().parse::<usize>())
        .collect();
    match list {
        Ok(list) if !list.is_empty() => Ok(TrainViews::List(list)),
        _ => Err(format!(
            "expected view indices separated by commas (1,10,19), got {s:?}"
        )),
    }
}

/// The indices `TrainViews::Evenly(n)` keeps of `total` views, in order: all of them when
/// `n` is 0 or at least `total`.
pub fn evenly_kept(total: usize, n: usize) -> Vec<usize> {
    if n == 0 || n >= total {
        return (0..total).collect();
    }
    (0..n).map(|k| k * total / n).collect()
}

/// `round(linspace(0, total - 1, n))`, halves to even as Python's and NumPy's `round`
/// take them (`linspace(0, 5, 3)` holds 2.5: view 2); all views when `n` is at least
/// `total`.
fn spread_kept(total: usize, n: usize) -> Vec<usize> {
    if n >= total {
        return (0..total).collect();
    }
    if n == 1 {
        return vec![0];
    }
    let last = (total - 1) as f64;
    (0..n)
        .map(|k| (k as f64 * last / (n - 1) as f64).round_ties_even() as usize)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The paper's fern holds 20 photos; with every 8th held out (0, 8, 16) the training
    /// split is 17, and RegNeRF's three views are its 0th, 8th and 16th: photos 1, 10 and
    /// 19 of the 20.
    #[test]
    fn three_spread_views_of_fern_are_regnerfs() {
        let kept = spread_kept(17, 3);
        assert_eq!(kept, vec![0, 8, 16]);
        let train: Vec<usize> = (0..20).filter(|i| i % 8 != 0).collect();
        let photos: Vec<usize> = kept.iter().map(|&k| train[k]).collect();
        assert_eq!(photos, vec![1, 10, 19]);
        assert_eq!(spread_kept(100, 9).len(), 9);
        assert_eq!(spread_kept(4, 9), vec![0, 1, 2, 3]);
        assert_eq!(spread_kept(10, 1), vec![0]);
        // Exact halves round to even, as in RegNeRF's Python.
        assert_eq!(spread_kept(6, 3), vec![0, 2, 5]);
        assert_eq!(spread_kept(4, 3), vec![0, 2, 3]);
    }

    #[test]
    fn counts_lists_and_their_errors_parse() {
        assert_eq!(parse_train_views("3"), Ok(TrainViews::Spread { spread: 3 }));
        assert_eq!(
            parse_train_views("1, 10,19"),
            Ok(TrainViews::List(vec![1, 10, 19]))
        );
        assert_eq!(parse_train_views("5,"), Ok(TrainViews::List(vec![5])));
        assert!(parse_train_views("0").is_err());
        assert!(parse_train_views("a,b").is_err());
        assert!(parse_train_views("three").is_err());
        let list = TrainViews::List(vec![2, 40]);
        let err = list.indices(30).expect_err("past the split").to_string();
        assert!(err.contains("view 40") && err.contains("30 views"), "{err}");
        let twice = TrainViews::List(vec![2, 2]).indices(30).expect_err("twice");
        assert!(twice.to_string().contains("named twice"), "{twice}");
        assert!(TrainViews::Spread { spread: 3 }.is_subset(30));
        let many = TrainViews::Spread { spread: 31 }
            .indices(30)
            .expect_err("too many");
        assert!(many.to_string().contains("holds only 30 views"), "{many}");
        assert_eq!(
            TrainViews::Spread { spread: 30 }
                .indices(30)
                .expect("all")
                .len(),
            30
        );
        assert!(!TrainViews::Evenly(30).is_subset(30));
    }

    /// Configs keep their counts: a bare number is the presets' even choice, and each
    /// form reads back as written.
    #[test]
    fn configs_round_trip_every_form() {
        let old: TrainViews = serde_json::from_str("25").expect("a count");
        assert_eq!(old, TrainViews::Evenly(25));
        assert_eq!(old.indices(100).expect("kept")[..3], [0, 4, 8]);
        for v in [
            TrainViews::Evenly(25),
            TrainViews::List(vec![1, 10, 19]),
            TrainViews::Spread { spread: 3 },
        ] {
            let text = serde_json::to_string(&v).expect("json");
            let back: TrainViews = serde_json::from_str(&text).expect("parse");
            assert_eq!(back, v, "{text}");
        }
    }
}
