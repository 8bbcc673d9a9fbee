"""What happens at and just behind each radar before the tertiary processor: the radars' own local
tracks, registration (bias estimation), radar health from the innovations, and report collection."""
