//! The parts a stopped daemon left, settled when it starts again from their records, before
//! any job asks: a part is kept (known again, so its store is served and removed with its
//! dataset's), removed when nobody needs it any more (its dataset is gone, or its dataset's
//! whole store is finished and no unfinished job holds a lease that may read it), or, when
//! its whole store is wanted and not built, kept and the whole store grown from it at once;
//! a part no job reads is then removed as soon as the whole store is grown from it.

use std::collections::HashSet;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use pointfarm_render::cut::StoredLod;

use super::{remove_part_folder, Part};
use crate::model::{CameraFirstPart, Dataset};
use crate::stores::DatasetStores;

/// What is known at start-up of a recorded part.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct PartFacts {
    /// A dataset of the whole content is still registered.
    whole_registered: bool,
    /// The whole store is finished.
    whole_built: bool,
    /// The part's own store is finished.
    part_built: bool,
    /// A job that read the part left the unseen files to after.
    whole_wanted: bool,
    /// An unfinished job of the whole content holds a lease, whose worker may read the part.
    leased: bool,
}

/// What becomes of a recorded part at start-up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Fate {
    /// Removed, for the reason given.
    Remove(&'static str),
    /// Known again, as it is.
    Keep,
    /// Known again and the whole store grown from it now; removed once that is done when it
    /// is to `retire` (no lease may read it).
    GrowWhole { retire: bool },
}

/// The one rule of which parts are kept, removed or grown into their whole stores.
fn fate(facts: PartFacts) -> Fate {
    if !facts.whole_registered {
        return Fate::Remove("its dataset is gone");
    }
    if facts.whole_built {
        return match facts.leased {
            true => Fate::Keep,
            false => Fate::Remove("its dataset's whole store is finished"),
        };
    }
    if facts.whole_wanted && facts.part_built {
        return Fate::GrowWhole {
            retire: !facts.leased,
        };
    }
    Fate::Keep
}

impl DatasetStores {
    /// Settles the parts a stopped daemon `recorded` (module doc), given the `datasets`
    /// registered and the contents whose unfinished jobs hold leases (`leased`). Called at
    /// start-up, after the parts' ledger is set and before any job is leased.
    pub fn settle_parts(
        &self,
        recorded: Vec<CameraFirstPart>,
        datasets: &[Dataset],
        leased: &HashSet<String>,
    ) {
        for record in recorded {
            let whole = datasets.iter().find(|d| d.sha256 == record.whole_sha256);
            let part_folder = self.folder(&record.part.sha256);
            let facts = PartFacts {
                whole_registered: whole.is_some(),
                whole_built: StoredLod::is_built(&self.folder(&record.whole_sha256)),
                part_built: StoredLod::is_built(&part_folder),
                whole_wanted: record.whole_wanted,
                leased: leased.contains(&record.whole_sha256),
            };
            let id = record.part.id.clone();
            let fate = fate(facts);
            if let Fate::Remove(why) = fate {
                if let Some(ledger) = self.camera_first.ledger.get() {
                    ledger.forget(&id);
                }
                remove_part_folder(&part_folder, &id, why);
                continue;
            }
            let part = Arc::new(Part::recorded(record));
            part.retired.store(
                matches!(fate, Fate::GrowWhole { retire: true }),
                Ordering::SeqCst,
            );
            self.lock_parts().insert(id.clone(), part);
            let (Fate::GrowWhole { .. }, Some(whole)) = (fate, whole) else {
                continue;
            };
            tracing::info!(dataset = %whole.id, part = %id,
                "camera first: growing the whole store a stopped daemon left unbuilt from its part");
            if let Err(error) = self.open_store(whole, true) {
                tracing::warn!(dataset = %whole.id, %error, "growing the whole store");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NOTHING: PartFacts = PartFacts {
        whole_registered: true,
        whole_built: false,
        part_built: true,
        whole_wanted: true,
        leased: false,
    };

    #[test]
    fn a_part_is_removed_once_nobody_needs_it() {
        let gone = PartFacts {
            whole_registered: false,
            ..NOTHING
        };
        assert_eq!(fate(gone), Fate::Remove("its dataset is gone"));
        // A lease of a job of a dataset that is gone reads nothing of it.
        assert!(matches!(
            fate(PartFacts {
                leased: true,
                ..gone
            }),
            Fate::Remove(_)
        ));
        let finished = PartFacts {
            whole_built: true,
            ..NOTHING
        };
        assert_eq!(
            fate(finished),
            Fate::Remove("its dataset's whole store is finished")
        );
        // Whatever its jobs asked, and built or not.
        for (whole_wanted, part_built) in [(false, false), (false, true), (true, false)] {
            let facts = PartFacts {
                whole_wanted,
                part_built,
                ..finished
            };
            assert!(matches!(fate(facts), Fate::Remove(_)), "{facts:?}");
        }
    }

    #[test]
    fn a_part_a_lease_may_read_is_kept() {
        let finished = PartFacts {
            whole_built: true,
            leased: true,
            ..NOTHING
        };
        assert_eq!(fate(finished), Fate::Keep);
    }

    #[test]
    fn a_wanted_whole_store_is_grown_from_its_finished_part() {
        assert_eq!(fate(NOTHING), Fate::GrowWhole { retire: true });
        let leased = PartFacts {
            leased: true,
            ..NOTHING
        };
        assert_eq!(fate(leased), Fate::GrowWhole { retire: false });
    }

    #[test]
    fn a_part_whose_whole_store_nobody_wants_or_not_finished_is_kept() {
        let never = PartFacts {
            whole_wanted: false,
            ..NOTHING
        };
        assert_eq!(fate(never), Fate::Keep);
        // Its jobs resume its build when they are leased.
        let unfinished = PartFacts {
            part_built: false,
            ..NOTHING
        };
        assert_eq!(fate(unfinished), Fate::Keep);
    }
}
