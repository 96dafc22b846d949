//! A file's coordinate reference system as its records declare it: the OGC WKT VLR
//! (`LASF_Projection`, 2112) when there is one, else the GeoTIFF GeoKeyDirectory (34735):
//! its projected, geographic and vertical EPSG codes. Nothing is resolved or validated
//! against a CRS database; this says what the file claims.

/// The user id of the projection records.
const PROJECTION_USER_ID: &str = "LASF_Projection";
/// The OGC WKT record.
const WKT_RECORD_ID: u16 = 2112;
/// The GeoTIFF GeoKeyDirectoryTag record.
const GEO_KEY_DIRECTORY_RECORD_ID: u16 = 34735;

/// GeoTIFF keys read from the directory.
const GEOGRAPHIC_TYPE_KEY: u16 = 2048;
const PROJECTED_CS_TYPE_KEY: u16 = 3072;
const VERTICAL_CS_TYPE_KEY: u16 = 4096;
/// The code GeoTIFF gives a system defined by parameters instead of an EPSG code.
pub const USER_DEFINED: u16 = 32767;

/// What a file declares of its coordinate reference system.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Crs {
    /// The OGC WKT record: its text, the name of the outermost system and its EPSG code when
    /// the WKT carries one at the top level.
    Wkt {
        wkt: String,
        name: Option<String>,
        epsg: Option<u32>,
    },
    /// The GeoTIFF keys (codes as stored; [`USER_DEFINED`] for a system given by parameters).
    GeoTiff(GeoKeys),
    /// A GeoKeyDirectory that cannot be read, and why.
    Unreadable(String),
    /// No projection record.
    None,
}

/// The EPSG codes of a GeoKeyDirectory, each when present.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GeoKeys {
    /// ProjectedCSTypeGeoKey (3072).
    pub projected: Option<u16>,
    /// GeographicTypeGeoKey (2048).
    pub geographic: Option<u16>,
    /// VerticalCSTypeGeoKey (4096).
    pub vertical: Option<u16>,
}

/// The CRS `header`'s VLRs and EVLRs declare.
pub fn crs_of(header: &las::Header) -> Crs {
    let record = |id: u16| {
        header
            .all_vlrs()
            .find(|vlr| vlr.user_id == PROJECTION_USER_ID && vlr.record_id == id)
    };
    if let Some(vlr) = record(WKT_RECORD_ID) {
        let wkt = String::from_utf8_lossy(&vlr.data)
            .trim_end_matches('\0')
            .trim()
            .to_owned();
        let (name, epsg) = wkt_name_and_epsg(&wkt);
        return Crs::Wkt { wkt, name, epsg };
    }
    match record(GEO_KEY_DIRECTORY_RECORD_ID) {
        Some(vlr) => match geo_keys(&vlr.data) {
            Ok(keys) => Crs::GeoTiff(keys),
            Err(reason) => Crs::Unreadable(reason),
        },
        None => Crs::None,
    }
}

/// The EPSG codes of a GeoKeyDirectory: a header of four shorts (version 1, revision,
/// minor revision, number of keys), then four shorts a key (id, location, count, value).
/// Only keys stored in place (location 0) carry a code.
pub fn geo_keys(data: &[u8]) -> Result<GeoKeys, String> {
    let shorts: Vec<u16> = data
        .chunks_exact(2)
        .map(|pair| u16::from_le_bytes([pair[0], pair[1]]))
        .collect();
    let [version, _, _, key_count, ..] = shorts[..] else {
        return Err(format!(
            "GeoKeyDirectory of {} bytes, shorter than its header",
            data.len()
        ));
    };
    if version != 1 {
        return Err(format!("GeoKeyDirectory version {version}, not 1"));
    }
    let entries = &shorts[4..];
    let key_count = usize::from(key_count);
    if entries.len() / 4 < key_count {
        return Err(format!(
            "GeoKeyDirectory declares {key_count} keys but holds {}",
            entries.len() / 4
        ));
    }
    let mut keys = GeoKeys::default();
    for entry in entries.chunks_exact(4).take(key_count) {
        let [id, location, _count, value] = [entry[0], entry[1], entry[2], entry[3]];
        if location != 0 {
            continue;
        }
        match id {
            PROJECTED_CS_TYPE_KEY => keys.projected = Some(value),
            GEOGRAPHIC_TYPE_KEY => keys.geographic = Some(value),
            VERTICAL_CS_TYPE_KEY => keys.vertical = Some(value),
            _ => {}
        }
    }
    Ok(keys)
}

/// The name of the outermost system of a WKT (its first quoted string) and the EPSG code of
/// its top-level `AUTHORITY["EPSG","…"]` (WKT 1) or `ID["EPSG",…]` (WKT 2); the authorities
/// of nested elements (datum, units) are not the system's.
fn wkt_name_and_epsg(wkt: &str) -> (Option<String>, Option<u32>) {
    let name = wkt
        .split_once('"')
        .and_then(|(_, rest)| rest.split_once('"'))
        .map(|(name, _)| name.to_owned());
    let mut depth = 0usize;
    let mut in_quotes = false;
    let mut word_start = 0;
    let mut epsg = None;
    for (at, c) in wkt.char_indices() {
        match c {
            '"' => in_quotes = !in_quotes,
            _ if in_quotes => {}
            '[' | '(' => {
                let word = wkt[word_start..at].trim();
                depth += 1;
                if depth == 2 && (word == "AUTHORITY" || word == "ID") {
                    epsg = epsg_of_authority(&wkt[at + 1..]).or(epsg);
                }
            }
            ']' | ')' => depth = depth.saturating_sub(1),
            _ => {}
        }
        if !in_quotes && matches!(c, '[' | '(' | ']' | ')' | ',') {
            word_start = at + c.len_utf8();
        }
    }
    (name, epsg)
}

/// The code of an authority's body (`"EPSG","2992"]…` or `"EPSG",2992]…`) when it is EPSG's.
fn epsg_of_authority(body: &str) -> Option<u32> {
    let body = body.split([']', ')']).next()?;
    let mut parts = body.split(',').map(|part| part.trim().trim_matches('"'));
    if !parts.next()?.eq_ignore_ascii_case("EPSG") {
        return None;
    }
    parts.next()?.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A GeoKeyDirectory payload: its header and `keys` as (id, location, count, value).
    fn directory(keys: &[[u16; 4]]) -> Vec<u8> {
        let count = u16::try_from(keys.len()).expect("a few keys");
        [1, 1, 0, count]
            .into_iter()
            .chain(keys.iter().flatten().copied())
            .flat_map(u16::to_le_bytes)
            .collect()
    }

    #[test]
    fn geo_keys_give_the_projected_geographic_and_vertical_codes() {
        let data = directory(&[
            [1024, 0, 1, 1],      // GTModelTypeGeoKey: projected
            [1026, 34737, 20, 0], // GTCitationGeoKey, in the ASCII record
            [2048, 0, 1, 4269],   // GeographicTypeGeoKey: NAD83
            [3072, 0, 1, 2992],   // ProjectedCSTypeGeoKey: Oregon Lambert (ft)
            [3076, 0, 1, 9002],   // ProjLinearUnitsGeoKey: foot
            [4096, 0, 1, 5703],   // VerticalCSTypeGeoKey: NAVD88 height
            [4099, 34736, 1, 0],  // VerticalUnitsGeoKey, in the double record
        ]);
        let keys = geo_keys(&data).expect("a well-formed directory");
        assert_eq!(
            keys,
            GeoKeys {
                projected: Some(2992),
                geographic: Some(4269),
                vertical: Some(5703),
            }
        );

        let user_defined = directory(&[[3072, 0, 1, USER_DEFINED]]);
        assert_eq!(
            geo_keys(&user_defined).expect("directory").projected,
            Some(USER_DEFINED)
        );
        assert_eq!(geo_keys(&directory(&[])), Ok(GeoKeys::default()));
    }

    #[test]
    fn a_short_or_foreign_geo_key_directory_is_unreadable_not_a_panic() {
        let mut data = directory(&[[3072, 0, 1, 2992], [4096, 0, 1, 5703]]);
        data.truncate(data.len() - 3);
        let error = geo_keys(&data).expect_err("a key cut short");
        assert_eq!(error, "GeoKeyDirectory declares 2 keys but holds 1");
        assert!(geo_keys(&[1, 0, 1]).is_err());
        let mut other_version = directory(&[]);
        other_version[0] = 2;
        assert!(geo_keys(&other_version).is_err());
    }

    #[test]
    fn a_wkt_gives_its_name_and_only_its_own_epsg_code() {
        // autzen's: the top level has no authority; its spheroid, datum and unit do.
        let nested = r#"PROJCS["NAD_1983_HARN_Lambert_Conformal_Conic",GEOGCS["GCS_North_American_1983_HARN",DATUM["NAD83",SPHEROID["GRS_1980",6378137,298.257222101,AUTHORITY["EPSG","7019"]],AUTHORITY["EPSG","6152"]]],UNIT["foot",0.3048,AUTHORITY["EPSG","9002"]]]"#;
        assert_eq!(
            wkt_name_and_epsg(nested),
            (Some("NAD_1983_HARN_Lambert_Conformal_Conic".into()), None)
        );
        let wkt1 = r#"PROJCS["NAD83 / UTM zone 12N",GEOGCS["NAD83",AUTHORITY["EPSG","4269"]],UNIT["metre",1,AUTHORITY["EPSG","9001"]],AUTHORITY["EPSG","26912"]]"#;
        assert_eq!(wkt_name_and_epsg(wkt1).1, Some(26912));
        let wkt2 = r#"PROJCRS["WGS 84 / UTM zone 33N",BASEGEOGCRS["WGS 84",ID["EPSG",4326]],ID["EPSG",32633]]"#;
        assert_eq!(
            wkt_name_and_epsg(wkt2),
            (Some("WGS 84 / UTM zone 33N".into()), Some(32633))
        );
        assert_eq!(wkt_name_and_epsg(""), (None, None));
    }
}
