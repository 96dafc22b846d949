//! The one check that reading a COPC object's nodes met the object replaced since it was
//! opened, whichever server holds it.

use pointfarm_render::copc::CopcError;
use pointfarm_render::lod::LodError;
use pointfarm_render::remote::RemoteError;

/// Checks that `error`, from reading the nodes of the COPC object at `url`, says the object
/// changed since it was opened, naming it.
pub fn assert_copc_object_changed(error: LodError, url: &str) {
    assert!(error.to_string().contains(url), "{error}");
    let LodError::RecordSource(source) = error else {
        panic!("not the reader's error: {error}");
    };
    let copc_error = source.downcast::<CopcError>().expect("a COPC error");
    assert!(
        matches!(
            *copc_error,
            CopcError::Remote(RemoteError::ObjectChanged { .. })
        ),
        "{copc_error}"
    );
}
