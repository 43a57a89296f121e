"""The MPEG-DASH manifest: its document model (`model`), its XML values (`values`), the StreamSTGS profile's
descriptors (`profile`, manifests/PROFILE.md) and validation against the ISO/IEC 23009-1 schema (`schema`)."""
