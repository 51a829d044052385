//! COLMAP's files, read and written: the text forms line by line, the
//! binary forms field by field (little-endian, each list preceded by its
//! length as a u64), as COLMAP's documentation ("Output format") gives
//! them.

use super::*;

pub(super) fn as_text(data: &[u8]) -> String {
    String::from_utf8_lossy(data).into_owned()
}

/// The lines of a text model that carry data (COLMAP starts comments with
/// `#`), numbered from 1 for messages.
pub(super) fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim_end_matches('\r')))
        .filter(|(_, line)| !line.trim_start().starts_with('#'))
}

pub(super) fn parse<T: std::str::FromStr>(
    field: &str,
    what: &str,
    line: usize,
) -> Result<T, String> {
    field
        .parse()
        .map_err(|_| format!("line {line}: {what} {field:?} is not a valid number"))
}

pub(super) fn read_cameras_text(text: &str) -> Result<BTreeMap<u32, ColmapCamera>, String> {
    let mut cameras = BTreeMap::new();
    for (line, content) in data_lines(text) {
        let fields: Vec<&str> = content.split_whitespace().collect();
        if fields.is_empty() {
            continue;
        }
        if fields.len() < 4 {
            return Err(format!(
                "line {line}: a camera needs CAMERA_ID MODEL WIDTH HEIGHT PARAMS, found {content:?}"
            ));
        }
        let id = parse(fields[0], "camera id", line)?;
        let model = fields[1].to_owned();
        let (_, _, count) = model_by_name(&model)
            .ok_or_else(|| format!("line {line}: unknown camera model {model}"))?;
        let params = fields[4..]
            .iter()
            .map(|f| parse::<f64>(f, "parameter", line))
            .collect::<Result<Vec<_>, _>>()?;
        if params.len() != count {
            return Err(format!(
                "line {line}: camera model {model} has {count} parameters, found {}",
                params.len()
            ));
        }
        let camera = ColmapCamera {
            id,
            model,
            width: parse(fields[2], "width", line)?,
            height: parse(fields[3], "height", line)?,
            params,
        };
        if cameras.insert(id, camera).is_some() {
            return Err(format!("line {line}: camera {id} is defined twice"));
        }
    }
    Ok(cameras)
}

pub(super) fn read_images_text(text: &str) -> Result<Vec<ColmapImage>, String> {
    let mut images = Vec::new();
    // Each image takes two lines; the second (its 2-D points) may be empty,
    // so blank lines are not skipped here.
    let mut lines = data_lines(text).peekable();
    while let Some((line, content)) = lines.next() {
        if content.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = content.split_whitespace().collect();
        if fields.len() < 10 {
            return Err(format!(
                "line {line}: an image needs IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, \
                 found {content:?}"
            ));
        }
        let number = |i: usize, what: &str| parse::<f64>(fields[i], what, line);
        let image = ColmapImage {
            id: parse(fields[0], "image id", line)?,
            rotation: [
                number(1, "QW")?,
                number(2, "QX")?,
                number(3, "QY")?,
                number(4, "QZ")?,
            ],
            translation: [number(5, "TX")?, number(6, "TY")?, number(7, "TZ")?],
            camera_id: parse(fields[8], "camera id", line)?,
            // Names may hold spaces: the rest of the line.
            name: fields[9..].join(" "),
        };
        check_image(&image).map_err(|p| format!("line {line}: {p}"))?;
        images.push(image);
        // Skip the points line: empty, or X Y POINT3D_ID triples. Some
        // writers leave it out; the line after is then the next image's,
        // which must not be skipped (that read half the images).
        if let Some(&(next_line, next)) = lines.peek() {
            let tokens: Vec<&str> = next.split_whitespace().collect();
            let is_points =
                tokens.len().is_multiple_of(3) && tokens.iter().all(|t| t.parse::<f64>().is_ok());
            if is_points {
                lines.next();
            } else if tokens.len() < 10 {
                return Err(format!(
                    "line {next_line}: expected image {}'s 2-D points (X Y POINT3D_ID \
                     triples, or an empty line) or the next image, found {next:?}",
                    images.last().map_or(0, |i| i.id)
                ));
            }
        }
    }
    Ok(images)
}

pub(super) fn read_points_text(text: &str) -> Result<Vec<[f64; 3]>, String> {
    let mut points = Vec::new();
    for (line, content) in data_lines(text) {
        let fields: Vec<&str> = content.split_whitespace().collect();
        if fields.is_empty() {
            continue;
        }
        if fields.len() < 4 {
            return Err(format!(
                "line {line}: a point needs POINT3D_ID X Y Z ..., found {content:?}"
            ));
        }
        points.push([
            parse(fields[1], "X", line)?,
            parse(fields[2], "Y", line)?,
            parse(fields[3], "Z", line)?,
        ]);
    }
    Ok(points)
}

pub(super) fn check_image(image: &ColmapImage) -> Result<(), String> {
    let q = image.rotation;
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !(norm.is_finite() && norm > 1e-6) || image.translation.iter().any(|v| !v.is_finite()) {
        return Err(format!(
            "image {} ({}): the pose (rotation {q:?}, translation {:?}) is not usable",
            image.id, image.name, image.translation
        ));
    }
    if image.name.is_empty() {
        return Err(format!("image {} has no file name", image.id));
    }
    Ok(())
}

/// A little-endian reader over a binary model file whose errors say where
/// the file ended.
pub(super) struct Reader<'a> {
    data: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn new(data: &'a [u8]) -> Self {
        Self { data, at: 0 }
    }

    fn take<const N: usize>(&mut self, what: &str) -> Result<[u8; N], String> {
        let bytes = self
            .data
            .get(self.at..self.at + N)
            .ok_or_else(|| format!("the file ends at byte {} inside {what}", self.data.len()))?;
        self.at += N;
        Ok(bytes.try_into().expect("slice of N bytes"))
    }

    fn u64(&mut self, what: &str) -> Result<u64, String> {
        self.take::<8>(what).map(u64::from_le_bytes)
    }

    fn u32(&mut self, what: &str) -> Result<u32, String> {
        self.take::<4>(what).map(u32::from_le_bytes)
    }

    fn i32(&mut self, what: &str) -> Result<i32, String> {
        self.take::<4>(what).map(i32::from_le_bytes)
    }

    fn f64(&mut self, what: &str) -> Result<f64, String> {
        self.take::<8>(what).map(f64::from_le_bytes)
    }

    /// A count of records at least `record_bytes` long each, checked
    /// against what is left of the file so that a corrupt count cannot ask
    /// for a huge allocation.
    fn count(&mut self, what: &str, record_bytes: usize) -> Result<usize, String> {
        let n = self.u64(what)?;
        let left = (self.data.len() - self.at) as u64;
        if n.saturating_mul(record_bytes as u64) > left {
            return Err(format!(
                "{what} is {n}, more than the {left} bytes left can hold"
            ));
        }
        Ok(n as usize)
    }

    fn skip(&mut self, bytes: u64, what: &str) -> Result<(), String> {
        let end = (self.at as u64)
            .checked_add(bytes)
            .filter(|&end| end <= self.data.len() as u64)
            .ok_or_else(|| format!("the file ends at byte {} inside {what}", self.data.len()))?;
        self.at = end as usize;
        Ok(())
    }

    fn name(&mut self) -> Result<String, String> {
        let rest = &self.data[self.at..];
        let end = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or("the file ends inside an image name")?;
        let name = String::from_utf8_lossy(&rest[..end]).into_owned();
        self.at += end + 1;
        Ok(name)
    }

    fn finish(&self) -> Result<(), String> {
        if self.at == self.data.len() {
            Ok(())
        } else {
            Err(format!(
                "{} bytes left over after the last record",
                self.data.len() - self.at
            ))
        }
    }
}

pub(super) fn read_cameras_binary(data: &[u8]) -> Result<BTreeMap<u32, ColmapCamera>, String> {
    let mut reader = Reader::new(data);
    let n = reader.count("the camera count", 24)?;
    let mut cameras = BTreeMap::new();
    for _ in 0..n {
        let id = reader.u32("a camera id")?;
        let model_id = reader.i32("a camera model")?;
        let (_, name, count) = model_by_id(model_id)
            .ok_or_else(|| format!("camera {id}: unknown camera model id {model_id}"))?;
        let width = reader.u64("a camera width")?;
        let height = reader.u64("a camera height")?;
        let params = (0..count)
            .map(|_| reader.f64("camera parameters"))
            .collect::<Result<Vec<_>, _>>()?;
        let camera = ColmapCamera {
            id,
            model: name.to_owned(),
            width,
            height,
            params,
        };
        if cameras.insert(id, camera).is_some() {
            return Err(format!("camera {id} is defined twice"));
        }
    }
    reader.finish()?;
    Ok(cameras)
}

pub(super) fn read_images_binary(data: &[u8]) -> Result<Vec<ColmapImage>, String> {
    let mut reader = Reader::new(data);
    let n = reader.count("the image count", 73)?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        let id = reader.u32("an image id")?;
        let mut rotation = [0.0; 4];
        for q in &mut rotation {
            *q = reader.f64("an image rotation")?;
        }
        let mut translation = [0.0; 3];
        for t in &mut translation {
            *t = reader.f64("an image translation")?;
        }
        let camera_id = reader.u32("an image's camera id")?;
        let name = reader.name()?;
        // Each 2-D point: x, y (f64) and its 3-D point id (i64).
        let points = reader.u64("an image's 2-D point count")?;
        reader.skip(points.saturating_mul(24), "an image's 2-D points")?;
        let image = ColmapImage {
            id,
            rotation,
            translation,
            camera_id,
            name,
        };
        check_image(&image)?;
        images.push(image);
    }
    reader.finish()?;
    Ok(images)
}

pub(super) fn read_points_binary(data: &[u8]) -> Result<Vec<[f64; 3]>, String> {
    let mut reader = Reader::new(data);
    let n = reader.count("the point count", 43)?;
    let mut points = Vec::with_capacity(n);
    for _ in 0..n {
        reader.u64("a point id")?;
        let xyz = [
            reader.f64("a point")?,
            reader.f64("a point")?,
            reader.f64("a point")?,
        ];
        // Colour (3 × u8) and reprojection error (f64).
        reader.skip(3 + 8, "a point's colour and error")?;
        // Track: (image id, 2-D point index) as two i32 per entry.
        let track = reader.u64("a point's track length")?;
        reader.skip(track.saturating_mul(8), "a point's track")?;
        points.push(xyz);
    }
    reader.finish()?;
    Ok(points)
}

/// Writes `model` as COLMAP text files into `folder` (cameras.txt,
/// images.txt with empty point lines, points3D.txt).
pub fn write_text(model: &ColmapModel, folder: &Path) -> std::io::Result<()> {
    use std::fmt::Write;
    std::fs::create_dir_all(folder)?;
    let mut cameras = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    for camera in model.cameras.values() {
        write!(
            cameras,
            "{} {} {} {}",
            camera.id, camera.model, camera.width, camera.height
        )
        .unwrap();
        for p in &camera.params {
            // `{:?}` of an f64 is the shortest text that reads back exactly.
            write!(cameras, " {p:?}").unwrap();
        }
        cameras.push('\n');
    }
    std::fs::write(folder.join("cameras.txt"), cameras)?;
    let mut images = String::from(
        "# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n",
    );
    for image in &model.images {
        let [qw, qx, qy, qz] = image.rotation;
        let [tx, ty, tz] = image.translation;
        writeln!(
            images,
            "{} {qw:?} {qx:?} {qy:?} {qz:?} {tx:?} {ty:?} {tz:?} {} {}\n",
            image.id, image.camera_id, image.name
        )
        .unwrap();
    }
    std::fs::write(folder.join("images.txt"), images)?;
    let mut points = String::from("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n");
    for (i, [x, y, z]) in model.points.iter().enumerate() {
        writeln!(points, "{} {x:?} {y:?} {z:?} 128 128 128 0.5", i + 1).unwrap();
    }
    std::fs::write(folder.join("points3D.txt"), points)
}

/// Writes `model` as COLMAP binary files into `folder`.
pub fn write_binary(model: &ColmapModel, folder: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(folder)?;
    let mut cameras = Vec::new();
    cameras.extend((model.cameras.len() as u64).to_le_bytes());
    for camera in model.cameras.values() {
        let (id, _, _) = model_by_name(&camera.model).ok_or_else(|| {
            std::io::Error::other(format!("unknown camera model {}", camera.model))
        })?;
        cameras.extend(camera.id.to_le_bytes());
        cameras.extend(id.to_le_bytes());
        cameras.extend(camera.width.to_le_bytes());
        cameras.extend(camera.height.to_le_bytes());
        for p in &camera.params {
            cameras.extend(p.to_le_bytes());
        }
    }
    std::fs::write(folder.join("cameras.bin"), cameras)?;
    let mut images = Vec::new();
    images.extend((model.images.len() as u64).to_le_bytes());
    for image in &model.images {
        images.extend(image.id.to_le_bytes());
        for v in image.rotation.iter().chain(&image.translation) {
            images.extend(v.to_le_bytes());
        }
        images.extend(image.camera_id.to_le_bytes());
        images.extend(image.name.as_bytes());
        images.push(0);
        images.extend(0u64.to_le_bytes());
    }
    std::fs::write(folder.join("images.bin"), images)?;
    let mut points = Vec::new();
    points.extend((model.points.len() as u64).to_le_bytes());
    for (i, xyz) in model.points.iter().enumerate() {
        points.extend((i as u64 + 1).to_le_bytes());
        for v in xyz {
            points.extend(v.to_le_bytes());
        }
        points.extend([128u8, 128, 128]);
        points.extend(0.5f64.to_le_bytes());
        points.extend(0u64.to_le_bytes());
    }
    std::fs::write(folder.join("points3D.bin"), points)
}
