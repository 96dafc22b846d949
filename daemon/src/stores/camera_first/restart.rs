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
    use std::sync::Mutex;

    use super::*;
    use crate::stores::PartLedger;

    /// The ids of the parts forgotten.
    #[derive(Default)]
    struct Forgotten(Mutex<Vec<String>>);

    impl PartLedger for Forgotten {
        fn keep(&self, _: &CameraFirstPart) {}

        fn forget(&self, id: &str) {
            self.0.lock().expect("ids").push(id.to_owned());
        }
    }

    fn dataset(sha256: &str) -> Dataset {
        Dataset {
            id: crate::model::dataset_id(sha256),
            name: sha256.to_owned(),
            size_bytes: 1,
            sha256: sha256.to_owned(),
            path: sha256.into(),
            files: Vec::new(),
            created_unix_ms: 0,
            remote: None,
            tiles: Vec::new(),
        }
    }

    fn record(part: &str, whole: &str, whole_wanted: bool) -> CameraFirstPart {
        CameraFirstPart {
            part: dataset(part),
            whole_sha256: whole.to_owned(),
            bounds: [[0.0; 3], [1.0; 3]],
            whole_wanted,
        }
    }

    #[test]
    fn settling_removes_the_parts_of_datasets_gone_and_knows_the_others_again() {
        let dir = tempfile::tempdir().expect("tempdir");
        let stores = DatasetStores::new(dir.path().join("lod"), 64 << 20);
        let ledger = Arc::new(Forgotten::default());
        stores.record_parts_in(Arc::clone(&ledger) as Arc<dyn PartLedger>);
        for part in ["part-a", "part-b"] {
            std::fs::create_dir_all(stores.folder(part)).expect("folder");
        }
        let recorded = vec![
            record("part-a", "whole-gone", true),
            record("part-b", "whole-kept", false),
        ];
        stores.settle_parts(recorded, &[dataset("whole-kept")], &HashSet::new());
        assert!(!stores.folder("part-a").exists());
        assert!(stores.folder("part-b").is_dir());
        let forgotten = ledger.0.lock().expect("ids").clone();
        assert_eq!(forgotten, vec![crate::model::dataset_id("part-a")]);
        let b = crate::model::dataset_id("part-b");
        assert_eq!(
            stores.part_dataset(&b).map(|d| d.sha256),
            Some("part-b".into())
        );
        assert!(stores
            .part_dataset(&crate::model::dataset_id("part-a"))
            .is_none());
        // Known again, it goes with its dataset's store.
        stores.remove("whole-kept");
        assert!(!stores.folder("part-b").exists());
        assert_eq!(ledger.0.lock().expect("ids").len(), 2);
    }

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
