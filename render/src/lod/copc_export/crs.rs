//! The dataset's coordinate reference system carried into the export: the OGC WKT record
//! (`LASF_Projection`, 2112) of its files when they all declare the same one, so QGIS and
//! PDAL place the file. GeoTIFF keys are not carried: LAS 1.4's point formats 6 and up take
//! a CRS as WKT only, and turning keys into WKT needs a CRS database.

use std::fs::File;
use std::io::BufReader;
use std::path::PathBuf;

use super::error::CopcExportError;

/// The user id of the projection records.
pub const PROJECTION_USER_ID: &str = "LASF_Projection";
/// The OGC WKT record.
pub const WKT_RECORD_ID: u16 = 2112;

/// The WKT record's bytes every one of `paths` declares, or `None` when one of them has none
/// or they differ (or the record is too long for a VLR).
pub fn common_wkt(paths: &[PathBuf]) -> Result<Option<Vec<u8>>, CopcExportError> {
    let mut common: Option<Vec<u8>> = None;
    for path in paths {
        let fail = |reason: String| CopcExportError::SourceHeader {
            path: path.clone(),
            reason,
        };
        let file = File::open(path).map_err(|e| fail(e.to_string()))?;
        let header = las::Header::new(BufReader::new(file)).map_err(|e| fail(e.to_string()))?;
        let wkt = header
            .all_vlrs()
            .find(|vlr| vlr.user_id == PROJECTION_USER_ID && vlr.record_id == WKT_RECORD_ID)
            .map(|vlr| vlr.data.clone());
        match (wkt, &common) {
            (None, _) => return Ok(None),
            (Some(wkt), Some(first)) if &wkt != first => return Ok(None),
            (Some(wkt), None) => common = Some(wkt),
            (Some(_), Some(_)) => {}
        }
    }
    Ok(common.filter(|wkt| wkt.len() <= usize::from(u16::MAX)))
}
